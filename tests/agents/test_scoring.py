"""The action-conditioned scoring policy: rollout geometry against a naive loop, masking, permutation invariance,
a known dangerous action, SB3 use (PPO learn, DQN Q-values, save/load, the training config)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from agents.actions import GoalRelativeActions
from agents.scoring import (
    GAP_CLIP_M,
    ActionRolloutExtractor,
    ActionScoringPolicy,
    action_geometry_kwargs,
    num_rollout_features,
)
from envs.config import CrowdNavConfig
from envs.observation import observation_space

K, H = 10, 12
CFG = CrowdNavConfig(observe_time_left=True)
ACTIONS = GoalRelativeActions(CFG)
A = ACTIONS.n


def extractor(with_forecasts: bool, **kw: Any) -> ActionRolloutExtractor:
    torch.manual_seed(0)
    return ActionRolloutExtractor(
        observation_space(CFG, with_forecasts), **action_geometry_kwargs(ACTIONS), context_dim=8, **kw
    )


def random_obs(with_forecasts: bool, batch: int, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    out = {
        "robot": torch.randn(batch, 5, generator=gen) * 3,
        "pedestrians": torch.randn(batch, K, 4, generator=gen) * 2,
        "mask": (torch.rand(batch, K, generator=gen) < 0.6).float(),
    }
    out["robot"][:, 4] = torch.rand(batch, generator=gen)
    if with_forecasts:
        out["forecasts"] = torch.randn(batch, K, H, 2, generator=gen) * 3
    return out


def one_pedestrian(
    position: tuple[float, float], velocity: tuple[float, float] = (0.0, 0.0)
) -> dict[str, torch.Tensor]:
    """A robot at rest with the goal 8 m along +x and one pedestrian (relative position, world velocity)."""
    obs = {
        "robot": torch.tensor([[8.0, 0.0, 0.0, 0.0, 1.0]]),
        "pedestrians": torch.zeros(1, K, 4),
        "mask": torch.zeros(1, K),
    }
    obs["pedestrians"][0, 0] = torch.tensor([*position, *velocity])
    obs["mask"][0, 0] = 1.0
    return obs


def naive_min_gaps(obs: dict[str, torch.Tensor], futures: np.ndarray) -> np.ndarray:
    """Per observation and action, the smallest gap over the horizon to any present pedestrian, by plain loops."""
    b = obs["mask"].shape[0]
    r_sum = CFG.robot_radius_m + CFG.pedestrian_radius_m
    vel = ACTIONS.velocities(obs["robot"].numpy())  # (B, A, 2)
    out = np.full((b, A), GAP_CLIP_M)
    for i in range(b):
        for a in range(A):
            for k in range(K):
                if obs["mask"][i, k] < 0.5:
                    continue
                for h in range(1, H + 1):
                    d = math.dist(vel[i, a] * h * CFG.dt_s, futures[i, k, h - 1])
                    out[i, a] = min(out[i, a], max(d - r_sum, -r_sum))
    return out


def test_min_clearance_matches_a_naive_loop_with_forecasts_and_with_constant_velocity() -> None:
    obs = random_obs(True, batch=4)
    feats = extractor(True).rollout_features(obs).numpy()
    assert feats.shape == (4, A, num_rollout_features(H))
    np.testing.assert_allclose(feats[:, :, 2 * H - 1], naive_min_gaps(obs, obs["forecasts"].numpy()), atol=1e-5)
    none_obs = {k: v for k, v in obs.items() if k != "forecasts"}
    peds = obs["pedestrians"].numpy()
    world_vel = peds[..., 2:4] + obs["robot"].numpy()[:, None, 2:4]
    t = CFG.dt_s * np.arange(1, H + 1)
    cv = peds[:, :, None, 0:2] + world_vel[:, :, None, :] * t[None, None, :, None]
    feats = extractor(False).rollout_features(none_obs).numpy()
    np.testing.assert_allclose(feats[:, :, 2 * H - 1], naive_min_gaps(none_obs, cv), atol=1e-5)


def test_walking_into_a_pedestrian_ahead_has_less_clearance_than_swerving() -> None:
    ext = extractor(False)
    feats = ext.rollout_features(one_pedestrian((2.0, 0.0))).numpy()[0]
    straight, left = 0, 7 * 4  # heading 0 at full speed; heading +90 degrees at full speed
    assert ACTIONS.angles[left] == pytest.approx(math.pi / 2) and ACTIONS.fractions[left] == 1.0
    min_gap = feats[:, 2 * H - 1]
    assert min_gap[straight] == pytest.approx(-0.6)  # drives through it: the gap clips at -(sum of radii)
    assert min_gap[left] > 0.5
    first_contact = feats[:, 2 * H + 1]  # first step with a gap below 0, over H
    assert first_contact[straight] == pytest.approx(4 / H)  # at 1 m/s the 2 m gap is closed at h = 4 (0.4 m/step)
    assert first_contact[left] == pytest.approx((H + 1) / H)  # never
    # a pedestrian walking towards the robot along the path (constant velocity) makes straight on worse, sooner
    moving = ext.rollout_features(one_pedestrian((4.0, 0.0), (-1.0, 0.0))).numpy()[0]
    still = ext.rollout_features(one_pedestrian((4.0, 0.0))).numpy()[0]
    assert moving[straight, 2 * H + 1] < still[straight, 2 * H + 1]
    # the same with static futures: the moving pedestrian is treated as standing
    static = extractor(False, no_forecast="static").rollout_features(one_pedestrian((4.0, 0.0), (-1.0, 0.0)))
    np.testing.assert_allclose(static.numpy()[0], still, atol=1e-6)


def test_nobody_present_gives_the_clipped_gap_and_no_conflict() -> None:
    obs = one_pedestrian((2.0, 0.0))
    obs["mask"][:] = 0.0
    feats = extractor(False).rollout_features(obs).numpy()[0]
    np.testing.assert_allclose(feats[:, : 2 * H], GAP_CLIP_M)
    np.testing.assert_allclose(feats[:, 2 * H + 1 : 2 * H + 3], (H + 1) / H)
    np.testing.assert_allclose(feats[:, 2 * H + 3 : 2 * H + 6], 0.0)


@pytest.mark.parametrize("with_forecasts", [False, True])
def test_absent_rows_change_nothing_whatever_they_hold(with_forecasts: bool) -> None:
    ext = extractor(with_forecasts)
    obs = random_obs(with_forecasts, batch=5)
    obs["mask"][0] = 0.0
    obs["mask"][1] = 1.0
    base = ext(obs)
    absent = obs["mask"] < 0.5
    for fill in (0.0, 1e6, float("nan"), float("inf")):
        poked = {k: v.clone() for k, v in obs.items()}
        poked["pedestrians"][absent] = fill
        if with_forecasts:
            poked["forecasts"][absent] = fill
        torch.testing.assert_close(ext(poked), base, rtol=0, atol=0)


@pytest.mark.parametrize("with_forecasts", [False, True])
def test_pedestrian_order_does_not_matter(with_forecasts: bool) -> None:
    ext = extractor(with_forecasts)
    obs = random_obs(with_forecasts, batch=5)
    perm = torch.randperm(K, generator=torch.Generator().manual_seed(3))
    shuffled = {k: (v[:, perm] if k != "robot" else v) for k, v in obs.items()}
    torch.testing.assert_close(ext(shuffled), ext(obs), rtol=1e-5, atol=1e-5)


def _env(with_forecasts: bool) -> Any:
    import gymnasium as gym

    class Fixed(gym.Env):
        """Observation space of the crowd env and its discrete action space; random observations, short episodes."""

        def __init__(self) -> None:
            self.observation_space = observation_space(CFG, with_forecasts)
            self.action_space = spaces.Discrete(A)
            self.t = 0

        def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
            super().reset(seed=seed)
            self.t = 0
            return self.observation_space.sample(), {}

        def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
            self.t += 1
            return self.observation_space.sample(), float(action == 0), self.t >= 10, False, {}

    return Fixed()


def _policy_kwargs() -> dict[str, Any]:
    return {
        "features_extractor_kwargs": {**action_geometry_kwargs(ACTIONS), "context_dim": 8},
        "head_kwargs": {"hidden_dim": 16},
    }


def test_ppo_learns_saves_and_loads_with_logits_from_shared_weights(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    model = PPO(ActionScoringPolicy, _env(True), n_steps=32, batch_size=16, n_epochs=1, policy_kwargs=_policy_kwargs(),
                seed=0, device="cpu")  # fmt: skip
    model.learn(64)
    obs = {k: torch.as_tensor(v)[None] for k, v in model.observation_space.sample().items()}
    logits = model.policy.get_distribution(obs).distribution.logits
    assert logits.shape == (1, A)
    # the scores are the head's per-action scores (action_net is the identity, no per-action weights)
    head = model.policy.mlp_extractor
    feats = model.policy.extract_features(obs, model.policy.pi_features_extractor)
    torch.testing.assert_close(torch.log_softmax(head.forward_actor(feats), dim=1), logits)
    assert not any(p.numel() for p in model.policy.action_net.parameters())
    model.save(tmp_path / "m.zip")
    loaded = PPO.load(tmp_path / "m.zip", device="cpu")
    torch.testing.assert_close(loaded.policy.get_distribution(obs).distribution.logits, logits)


@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_head_outputs_and_gradients_equal_the_plain_formula(activation: str) -> None:
    """The head's update shortcuts (no gradient into the parameter-free geometry, the context added in place, the
    maximum over actions by ``max``) change neither its outputs (the same bits as the formula of the class docstring
    written out plainly) nor any gradient the update uses (the same up to float rounding: the sums of a code's
    gradients run in another order)."""
    from agents.scoring import ActionScoringHead

    f, c, b = num_rollout_features(H), 25, 64
    torch.manual_seed(0)
    head = ActionScoringHead(A, f, c, hidden_dim=16, activation=activation)
    geometry = torch.randn(b, A * f) * 2  # as the extractor's: computed without gradient
    context = torch.randn(b, c, requires_grad=True)  # the context encoder's output: it has a gradient

    def plain(h: ActionScoringHead, ctx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([geometry, ctx], dim=1)[:, : A * f].reshape(b, A, f)
        codes = h.act(h.hidden(h.act(h.action_in(x) + h.context_in(ctx)[:, None, :])))
        value = h.act(h.value_in(torch.cat([ctx, codes.mean(dim=1), codes.amax(dim=1)], dim=1)))
        return h.score(codes).squeeze(-1), value

    def loss_and_grads(outputs: tuple[torch.Tensor, torch.Tensor]) -> list[torch.Tensor]:
        logits, value = outputs
        loss = torch.log_softmax(logits, dim=1)[:, 3].sum() + value.square().sum()
        return list(torch.autograd.grad(loss, [context, *head.parameters()]))

    expected = plain(head, context)
    got = head(torch.cat([geometry, context], dim=1))
    for e, g in zip(expected, got, strict=True):
        assert torch.equal(e, g)
    for e, g in zip(loss_and_grads(plain(head, context)), loss_and_grads(got), strict=True):
        torch.testing.assert_close(g, e, rtol=1e-5, atol=1e-6)


def test_dqn_uses_the_scores_as_q_values() -> None:
    from stable_baselines3 import DQN

    from agents.scoring import ActionScoringQPolicy

    model = DQN(ActionScoringQPolicy, _env(False), learning_starts=16, buffer_size=200, batch_size=8,
                policy_kwargs=_policy_kwargs(), seed=0, device="cpu")  # fmt: skip
    model.learn(64)
    obs = {k: torch.as_tensor(v)[None] for k, v in model.observation_space.sample().items()}
    assert model.q_net(obs).shape == (1, A)


def test_wrong_action_space_or_horizon_is_named() -> None:
    from stable_baselines3 import PPO

    env = _env(True)
    env.action_space = spaces.Discrete(A - 1)
    with pytest.raises(ValueError, match="scores 57 actions"):
        PPO(ActionScoringPolicy, env, policy_kwargs=_policy_kwargs(), device="cpu")
    with pytest.raises(ValueError, match="horizon_steps"):
        ActionRolloutExtractor(observation_space(CFG, True), **{**action_geometry_kwargs(ACTIONS), "horizon_steps": 8})


def test_training_config_fills_in_the_action_geometry(tiny: Any, config_of: Any, tmp_path: Path) -> None:
    from agents.training.config import algorithm_kwargs, load_train_config
    from agents.training.run import train
    from crowdnav_mesrnn.config import ConfigError

    over = tiny("ppo", "none", steps=64, **{"action.kind": "discrete", "policy": "agents.scoring.ActionScoringPolicy"})
    over.pop("policy_kwargs.net_arch")
    over["policy_kwargs.features_extractor_kwargs"] = {"context_dim": 8}
    cfg = load_train_config(config_of("ppo"), None, over)
    extractor_kwargs = algorithm_kwargs(cfg)["policy_kwargs"]["features_extractor_kwargs"]
    assert extractor_kwargs["action_fractions"] == ACTIONS.fractions.tolist()
    run = train(cfg, tmp_path / "scoring", progress=False)
    assert (run / "best_model.zip").is_file()
    bad = dict(over, **{"policy_kwargs.features_extractor_kwargs": {"dt_s": 0.25}})
    with pytest.raises(ConfigError, match="dt_s"):
        algorithm_kwargs(load_train_config(config_of("ppo"), None, bad))


def test_rollout_buffer_caches_the_geometry_once_per_rollout() -> None:
    from stable_baselines3 import PPO

    from agents.scoring import GEOMETRY_KEY, GeometryCachingBuffer, attach_geometry_cache

    model = PPO(ActionScoringPolicy, _env(True), n_steps=32, batch_size=16, n_epochs=1, policy_kwargs=_policy_kwargs(),
                rollout_buffer_class=GeometryCachingBuffer, seed=0, device="cpu")  # fmt: skip
    assert attach_geometry_cache(model)
    calls = []
    geometry = model.rollout_buffer.geometry_fn
    model.rollout_buffer.attach(lambda obs: calls.append(len(obs["mask"])) or geometry(obs))
    model.learn(32)  # one rollout, one epoch of two minibatches: the geometry of the 32 observations, once
    assert calls == [32]
    batch = next(model.rollout_buffer.get(8))
    assert GEOMETRY_KEY in batch.observations
    plain = {k: v for k, v in batch.observations.items() if k != GEOMETRY_KEY}
    cached = model.policy.evaluate_actions(batch.observations, batch.actions.long().flatten())
    fresh = model.policy.evaluate_actions(plain, batch.actions.long().flatten())
    for a, b in zip(cached, fresh, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert calls == [32]  # get() after the rollout computed nothing new


def test_rollout_buffer_keeps_the_geometry_the_rollout_computed() -> None:
    """With the policy attached, the update uses the geometry the rollout's forward passes computed (stored step by
    step, in SB3's flattened order): the same as computing it from the buffer's observations, and nothing computed
    again. A step whose observations are not those of the last forward pass is computed at the update."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.scoring import GeometryCachingBuffer, attach_geometry_cache

    venv = DummyVecEnv([lambda: _env(True), lambda: _env(True)])  # two environments: the (step, env) order matters
    model = PPO(ActionScoringPolicy, venv, n_steps=16, batch_size=16, n_epochs=1, policy_kwargs=_policy_kwargs(),
                rollout_buffer_class=GeometryCachingBuffer, seed=0, device="cpu")  # fmt: skip
    assert attach_geometry_cache(model)
    buffer = model.rollout_buffer
    geometry = buffer.geometry_fn
    calls: list[int] = []
    buffer.geometry_fn = lambda obs: calls.append(len(obs["mask"])) or geometry(obs)
    model.learn(32)  # one rollout of 16 steps x 2 environments, one epoch
    assert calls == []  # taken from the rollout, not computed
    recomputed = geometry({k: buffer.to_torch(v) for k, v in buffer.observations.items()})
    assert buffer._geometry is not None
    torch.testing.assert_close(buffer._geometry, recomputed, rtol=0, atol=0)

    # observations other than the forward pass's: not taken; that step is computed at the first minibatch
    buffer.reset()
    policy = model.policy
    for step in range(buffer.buffer_size):
        obs = {k: np.stack([model.observation_space[k].sample() for _ in range(2)]) for k in buffer.observations}
        policy(policy.obs_to_tensor(obs)[0])
        if step == 3:
            obs = {**obs, "robot": obs["robot"] + 1.0}
        buffer.add(obs, np.zeros((2, 1)), np.zeros(2), np.zeros(2), torch.zeros(2, 1), torch.zeros(2))
    assert policy.take_rollout_geometry(obs) is None  # taken by the buffer: kept once only
    assert not buffer._have[3] and buffer._have.sum() == buffer.buffer_size - 1
    buffer.compute_returns_and_advantage(torch.zeros(2, 1), np.zeros(2))
    next(buffer.get(8))
    assert calls == [32]


def test_training_with_the_rollout_geometry_kept_is_the_same_training() -> None:
    """PPO with the rollout's geometry kept for the update and PPO computing it at the update train the same
    weights, bit for bit."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.scoring import GeometryCachingBuffer, attach_geometry_cache

    def trained(keep: bool) -> list[torch.Tensor]:
        venv = DummyVecEnv([lambda: _env(True), lambda: _env(True)])
        for i, env in enumerate(venv.envs):  # the same observations in both trainings
            env.unwrapped.observation_space.seed(i)
        model = PPO(ActionScoringPolicy, venv, n_steps=16, batch_size=8, n_epochs=2, policy_kwargs=_policy_kwargs(),
                    rollout_buffer_class=GeometryCachingBuffer, seed=0, device="cpu")  # fmt: skip
        if keep:
            assert attach_geometry_cache(model)
        else:  # the cache as before: computed from the buffer's observations at the first minibatch
            model.rollout_buffer.attach(model.policy.features_extractor.geometry)
        model.learn(64)
        return [p.detach().clone() for p in model.policy.parameters()]

    for a, b in zip(trained(True), trained(False), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("predictor", ["none", "mesrnn"])
def test_the_recipe_candidate_builds_for_every_arm(predictor: str) -> None:
    from agents.scoring import GeometryCachingBuffer
    from agents.training.config import algorithm_kwargs, load_train_config

    cfg = load_train_config(Path(__file__).parents[2] / "configs" / "agent" / "ppo_scoring.yaml", None,
                            {"predictor": predictor})  # fmt: skip
    kwargs = algorithm_kwargs(cfg)
    assert kwargs["rollout_buffer_class"] is GeometryCachingBuffer
    assert kwargs["policy_kwargs"]["features_extractor_kwargs"]["horizon_steps"] == H
    assert cfg.pretrain is not None and cfg.pretrain.teacher == "planner"


def test_warm_start_fits_with_the_geometry_computed_once(monkeypatch: pytest.MonkeyPatch) -> None:
    from stable_baselines3 import PPO

    from agents import scoring
    from agents.training.pretrain import PretrainConfig, TeacherData, fit_policy

    model = PPO(ActionScoringPolicy, _env(True), n_steps=32, batch_size=16, policy_kwargs=_policy_kwargs(), seed=0,
                device="cpu")  # fmt: skip
    space = model.observation_space
    obs = [space.sample() for _ in range(40)]
    data = TeacherData(
        {k: np.stack([o[k] for o in obs]) for k in obs[0]},
        np.tile(np.array([[1.0, 0.0]], dtype=np.float32), (40, 1)),
        np.zeros(40),
        ["success"],
    )
    ext = model.policy.features_extractor
    calls = []
    real = ext.rollout_features
    monkeypatch.setattr(ext, "rollout_features", lambda o: calls.append(len(o["mask"])) or real(o))
    robot = data.observations["robot"]
    robot[:, :2] = np.abs(robot[:, :2]) + 1.0  # goals ahead, so every label is action 0
    fit_policy(model, data, PretrainConfig(epochs=3, batch_size=16), seed=0, actions=ACTIONS)
    assert calls == [40]  # once for the data set, not per epoch and minibatch
    monkeypatch.setattr(scoring, "MAX_CACHED_GEOMETRY_BYTES", 0)
    calls.clear()
    fit_policy(model, data, PretrainConfig(epochs=3, batch_size=16), seed=0, actions=ACTIONS)
    assert sum(calls) == 2 * 3 * 40  # too large to keep: per minibatch, for the action loss and the value loss
