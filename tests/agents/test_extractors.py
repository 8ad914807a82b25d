"""The Dict-observation features extractor: masking, parameter counts per arm, degenerate inputs, SB3 use."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agents.extractors import CrowdActorCriticPolicy, CrowdFeaturesExtractor, CrowdSACPolicy
from envs.config import CrowdNavConfig
from envs.observation import observation_space

K, H = 10, 12


def space(with_forecasts: bool, **kw: object) -> object:
    return observation_space(CrowdNavConfig(**kw), with_forecasts)  # type: ignore[arg-type]


def random_obs(sp: object, batch: int, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for key, sub in sp.spaces.items():  # type: ignore[attr-defined]
        shape = (batch, *sub.shape)
        if key == "mask":
            out[key] = (torch.rand(shape, generator=gen) < 0.5).float()
        else:
            out[key] = torch.randn(shape, generator=gen) * 3
    return out


OPTIONS = [
    {"pooling": "meanmax"},
    {"pooling": "attention"},
    {"pooling": "meanmax", "distances": True},
    {"pooling": "meanmax", "frame": "goal", "robot_context": True},
]


@pytest.mark.parametrize("options", OPTIONS)
@pytest.mark.parametrize("with_forecasts", [False, True])
def test_absent_pedestrians_change_nothing_whatever_their_rows_hold(options: dict, with_forecasts: bool) -> None:
    torch.manual_seed(0)
    sp = space(with_forecasts)
    ext = CrowdFeaturesExtractor(sp, hidden_dim=16, **options)  # type: ignore[arg-type]
    obs = random_obs(sp, batch=6)
    obs["mask"][0] = 0.0  # one observation with nobody
    obs["mask"][1] = 1.0  # one with everybody
    base = ext(obs)
    absent = obs["mask"] < 0.5
    for fill in (0.0, 1e6, -1e6, float("nan"), float("inf")):
        poked = {k: v.clone() for k, v in obs.items()}
        peds = poked["pedestrians"].view(6, K, 4)
        peds[absent] = fill
        if with_forecasts:
            poked["forecasts"].view(6, K, H * 2)[absent] = fill
        out = ext(poked)
        torch.testing.assert_close(out, base, rtol=0, atol=0)
    # and a present pedestrian does change it
    poked = {k: v.clone() for k, v in obs.items()}
    poked["pedestrians"].view(6, K, 4)[1, 0, 0] += 1.0
    assert not torch.equal(ext(poked)[1], base[1])


@pytest.mark.parametrize("pooling", ["meanmax", "attention"])
def test_all_masked_is_finite_and_pools_to_zero(pooling: str) -> None:
    sp = space(True)
    ext = CrowdFeaturesExtractor(sp, hidden_dim=8, pooling=pooling)  # type: ignore[arg-type]
    obs = random_obs(sp, batch=3)
    obs["mask"].zero_()
    out = ext(obs)
    assert out.shape == (3, ext.features_dim)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out[:, 8:], torch.zeros(3, ext.features_dim - 8))
    out.sum().backward()  # gradients stay finite too
    assert all(torch.isfinite(p.grad).all() for p in ext.parameters() if p.grad is not None)


@pytest.mark.parametrize(("pooling", "distances"), [("meanmax", False), ("attention", False), ("meanmax", True)])
def test_same_parameters_in_every_arm_except_the_forecast_input(pooling: str, distances: bool) -> None:
    hidden = 32
    kw = {"hidden_dim": hidden, "pooling": pooling, "distances": distances}
    without = CrowdFeaturesExtractor(space(False), **kw)  # type: ignore[arg-type]
    with_fc = CrowdFeaturesExtractor(space(True), **kw)  # type: ignore[arg-type]
    assert without.features_dim == with_fc.features_dim
    names_a = {n: p.shape for n, p in without.named_parameters()}
    names_b = {n: p.shape for n, p in with_fc.named_parameters()}
    assert names_a.keys() == names_b.keys()
    differing = {n for n in names_a if names_a[n] != names_b[n]}
    assert differing == {"pedestrian_encoder.0.weight"}
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    per_step = 3 if distances else 2  # forecast x, y (and its distance)
    assert count(with_fc) - count(without) == per_step * H * hidden
    assert with_fc.pedestrian_input_layer.in_features - without.pedestrian_input_layer.in_features == per_step * H


def test_structured_and_flat_observations_give_the_same_features() -> None:
    torch.manual_seed(1)
    flat, shaped = space(True), space(True, flatten_observation=False)
    ext = CrowdFeaturesExtractor(flat, hidden_dim=8)  # type: ignore[arg-type]
    ext_shaped = CrowdFeaturesExtractor(shaped, hidden_dim=8)  # type: ignore[arg-type]
    ext_shaped.load_state_dict(ext.state_dict())
    obs = random_obs(flat, batch=2)
    obs_shaped = dict(obs)
    obs_shaped["pedestrians"] = obs["pedestrians"].view(2, K, 4)
    obs_shaped["forecasts"] = obs["forecasts"].view(2, K, H, 2)
    torch.testing.assert_close(ext(obs), ext_shaped(obs_shaped))


def test_bad_options_are_rejected() -> None:
    with pytest.raises(ValueError, match="pooling"):
        CrowdFeaturesExtractor(space(False), pooling="sum")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="activation"):
        CrowdFeaturesExtractor(space(False), activation="gelu2")  # type: ignore[arg-type]


@pytest.mark.parametrize("with_forecasts", [False, True])
def test_policies_use_the_extractor_and_take_activation_names(with_forecasts: bool) -> None:
    from gymnasium import spaces

    sp = space(with_forecasts)
    act = spaces.Box(-1, 1, (2,), np.float32)
    ppo = CrowdActorCriticPolicy(
        sp, act, lambda _: 3e-4, net_arch=[16], activation_fn="tanh", features_extractor_kwargs={"hidden_dim": 8}
    )
    assert isinstance(ppo.features_extractor, CrowdFeaturesExtractor)
    assert ppo.activation_fn is torch.nn.Tanh
    sac = CrowdSACPolicy(sp, act, lambda _: 3e-4, net_arch=[16], features_extractor_kwargs={"hidden_dim": 8})
    assert isinstance(sac.actor.features_extractor, CrowdFeaturesExtractor)
    obs = {k: v.numpy() for k, v in random_obs(sp, batch=1).items()}
    obs = {k: v[0] for k, v in obs.items()}
    for policy in (ppo, sac):
        action, _ = policy.predict(obs, deterministic=True)
        assert action.shape == (2,)


def _rotated(obs: dict[str, torch.Tensor], angle: float) -> dict[str, torch.Tensor]:
    """The observation of the same scene turned by ``angle`` about the robot (every 2-D vector rotated)."""
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float32)

    def turn(v: torch.Tensor) -> torch.Tensor:
        return (v.reshape(*v.shape[:-1], -1, 2) @ rot.T).reshape(v.shape)

    out = dict(obs)
    out["robot"] = torch.cat([turn(obs["robot"][:, :4]), obs["robot"][:, 4:]], dim=1)
    out["pedestrians"] = turn(obs["pedestrians"])
    if "forecasts" in obs:
        out["forecasts"] = turn(obs["forecasts"])
    return out


@pytest.mark.parametrize("with_forecasts", [False, True])
def test_goal_frame_features_do_not_depend_on_the_goals_bearing(with_forecasts: bool) -> None:
    torch.manual_seed(0)
    sp = space(with_forecasts, observe_time_left=True)
    goal_frame = CrowdFeaturesExtractor(sp, hidden_dim=16, frame="goal", robot_context=True)  # type: ignore[arg-type]
    world = CrowdFeaturesExtractor(sp, hidden_dim=16)  # type: ignore[arg-type]
    obs = random_obs(sp, batch=5)
    for angle in (0.3, math.pi / 2, -2.5):
        turned = _rotated(obs, angle)
        torch.testing.assert_close(goal_frame(turned), goal_frame(obs), rtol=1e-4, atol=1e-4)
        assert not torch.allclose(world(turned), world(obs), atol=1e-3)  # the world frame does see the turn


def test_goal_frame_puts_the_goal_on_the_x_axis() -> None:
    sp = space(False)
    ext = CrowdFeaturesExtractor(sp, frame="goal")  # type: ignore[arg-type]
    obs = random_obs(sp, batch=3)
    obs["robot"][:, :2] = torch.tensor([[0.0, 4.0], [-3.0, 0.0], [0.0, 0.0]])
    robot = ext.to_goal_frame(obs)["robot"]
    torch.testing.assert_close(robot[:, :2], torch.tensor([[4.0, 0.0], [3.0, 0.0], [0.0, 0.0]]))
