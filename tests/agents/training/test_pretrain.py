"""Behaviour-cloning warm start: the policy moves towards the teacher, deterministically, for PPO and SAC."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from agents.training.config import algorithm_kwargs, load_train_config, policy_class
from agents.training.pretrain import PretrainConfig, collect_teacher, discounted_returns, fit_policy
from agents.training.run import make_vec_env

ENV = {"predictor": "cv", "crowd": "synthetic", "part": "train", "episode_time": "train", "observe_time_left": True}


def tiny_model(algo: str, config_of: Any, tiny: Any) -> Any:
    from stable_baselines3 import PPO, SAC

    # the regression on the environment's (world-frame) action, with the extractor in the world frame too
    extra = (
        {"action.kind": "continuous", "policy_kwargs.features_extractor_kwargs.frame": "world"} if algo == "ppo" else {}
    )
    cfg = load_train_config(config_of(algo), None, tiny(algo, "cv", vec_env="dummy", **extra))
    venv = make_vec_env(cfg)
    cls = {"ppo": PPO, "sac": SAC}[algo]
    return cls(policy_class(cfg.policy), venv, seed=0, device="cpu", **algorithm_kwargs(cfg))


def action_error(model: Any, data: Any) -> float:
    actions, _ = model.predict(data.observations, deterministic=True)
    return float(np.mean((actions - np.clip(data.actions, -1, 1)) ** 2))


def test_discounted_returns() -> None:
    np.testing.assert_allclose(discounted_returns([1.0, 0.0, 2.0], 0.5), [1.5, 1.0, 2.0])


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_pretraining_brings_the_policy_closer_to_the_teacher(algo: str, config_of: Any, tiny: Any) -> None:
    torch.manual_seed(0)
    cfg = PretrainConfig(episodes=8, epochs=15, batch_size=64, lr=3e-3)
    data = collect_teacher(cfg, ENV, seed=0, gamma=0.99)
    assert 100 <= len(data) <= 1000 and data.actions.shape == (len(data), 2)
    model = tiny_model(algo, config_of, tiny)
    before = action_error(model, data)
    stats = fit_policy(model, data, cfg, seed=0)
    after = action_error(model, data)
    assert after < 0.5 * before, (before, after)
    assert stats["loss_last_epoch"] < stats["loss_first_epoch"]
    if algo == "ppo":
        assert torch.allclose(model.policy.log_std, torch.full_like(model.policy.log_std, -1.0))
    else:  # the target critics follow the fitted critics
        for p, q in zip(model.policy.critic.parameters(), model.policy.critic_target.parameters(), strict=True):
            assert torch.equal(p, q)


def test_pretraining_is_deterministic_given_the_seed(config_of: Any, tiny: Any) -> None:
    cfg = PretrainConfig(episodes=3, epochs=2, batch_size=32)
    params = []
    for _ in range(2):
        torch.manual_seed(0)
        data = collect_teacher(cfg, ENV, seed=5, gamma=0.99)
        model = tiny_model("ppo", config_of, tiny)
        fit_policy(model, data, cfg, seed=5)
        params.append(torch.cat([p.detach().flatten() for p in model.policy.parameters()]))
    assert torch.equal(params[0], params[1])


def test_dagger_rounds_label_the_students_states_with_the_teachers_actions(config_of: Any, tiny: Any) -> None:
    from stable_baselines3 import PPO

    from agents.actions import GoalRelativeActions
    from agents.planners import SamplingPlanner
    from agents.training.pretrain import pretrain, student_policy
    from envs.config import config_from

    cfg = load_train_config(config_of("ppo"), None, tiny("ppo", "cv", vec_env="dummy", **{"action.kind": "discrete"}))
    venv = make_vec_env(cfg)
    model = PPO(policy_class(cfg.policy), venv, seed=0, device="cpu", **algorithm_kwargs(cfg))
    actions = GoalRelativeActions(config_from(ENV, {}))
    pre = PretrainConfig(episodes=4, epochs=3, batch_size=64, dagger_rounds=2, dagger_episodes=3, dagger_epochs=2)
    torch.manual_seed(0)
    stats = pretrain(model, pre, ENV, seed=0, gamma=0.99, actions=actions)
    assert [r["round"] for r in stats["dagger"]] == [1, 2]
    assert stats["episodes"] == 4 + 2 * 3
    sizes = [r["transitions"] for r in stats["dagger"]]
    assert sizes[0] < sizes[1] == stats["transitions"]  # every round adds to the aggregate
    # a round's data: observations the student met, labelled by the teacher (not by the student)
    data = collect_teacher(pre, ENV, seed=0, gamma=0.99, driver=student_policy(model, None, actions), round_=1)
    teacher = SamplingPlanner(config_from(ENV, {}))
    np.testing.assert_allclose(data.actions, teacher.predict(data.observations)[0], atol=1e-6)
    with pytest.raises(Exception, match="dagger_rounds"):
        PretrainConfig(dagger_rounds=-1).validate()


def test_a_discrete_policy_without_its_action_set_is_refused(config_of: Any, tiny: Any) -> None:
    from stable_baselines3 import PPO

    cfg = load_train_config(config_of("ppo"), None, tiny("ppo", "cv", vec_env="dummy"))  # discrete actions
    model = PPO(policy_class(cfg.policy), make_vec_env(cfg), seed=0, device="cpu", **algorithm_kwargs(cfg))
    pre = PretrainConfig(episodes=2, epochs=1)
    with pytest.raises(ValueError, match="discrete action set"):
        fit_policy(model, collect_teacher(pre, ENV, seed=0, gamma=0.99), pre, seed=0)


def test_the_warm_start_progress_bars_say_what_they_count(capsys: pytest.CaptureFixture[str]) -> None:
    from agents.planners import SamplingPlanner
    from envs.config import config_from

    cfg = PretrainConfig(episodes=2, dagger_rounds=3, dagger_episodes=2, n_envs=2)
    collect_teacher(cfg, ENV, seed=0, gamma=0.99, progress=True)
    assert "warm start: planner teacher's episodes: 100%" in capsys.readouterr().err
    student = SamplingPlanner(config_from(ENV, {}))  # any driver
    collect_teacher(cfg, ENV, seed=0, gamma=0.99, progress=True, driver=student, round_=2)
    assert "DAgger round 2/3: student's episodes, labelled by planner: 100%" in capsys.readouterr().err


def test_teacher_by_class_path_gives_the_named_planners_data() -> None:
    named = collect_teacher(PretrainConfig(teacher="straight", episodes=2), ENV, seed=3, gamma=0.99)
    by_path = collect_teacher(
        PretrainConfig(teacher="agents.planners:StraightToGoal", episodes=2), ENV, seed=3, gamma=0.99
    )
    np.testing.assert_array_equal(by_path.actions, named.actions)
    assert by_path.outcomes == named.outcomes


@pytest.mark.parametrize(
    ("teacher", "message"),
    [
        ("oracle_search", "not a planner of agents.planners.*available: straight, planner"),
        ("agents.planners:NoSuchPlanner", "cannot be imported"),
        ("agents.planners:PLANNERS", "no predict method"),
    ],
)
def test_an_unavailable_teacher_is_named(teacher: str, message: str) -> None:
    from crowdnav_mesrnn.config import ConfigError

    with pytest.raises(ConfigError, match=message):
        PretrainConfig(teacher=teacher).validate()


class _CountingTeacher:
    """A teacher that reads its environments (``bind_envs``: one per row of the next batch) and whose answer depends
    on how often it was asked, so labels computed after the episodes would differ from the ones it gave."""

    def __init__(self) -> None:
        self.envs: list[Any] = []
        self.calls = 0

    def bind_envs(self, envs: list[Any]) -> None:
        self.envs = list(envs)

    def predict(self, obs: dict, state: Any = None, episode_start: Any = None, deterministic: bool = True) -> Any:
        self.calls += 1
        n = len(obs["mask"])
        assert len(self.envs) == n, "each row's environment is bound before predict"
        for env, robot in zip(self.envs, obs["robot"], strict=True):  # row i is envs[i]
            goal_offset = env.episode.goal - env.robot_position
            np.testing.assert_allclose(robot[:2], goal_offset, atol=1e-4)
        self.envs = []
        return np.tile(np.array([[0.5, 0.0]], dtype=np.float32) * (1 + self.calls % 2), (n, 1)), None


def test_a_teacher_that_reads_the_environments_labels_at_every_step(monkeypatch: pytest.MonkeyPatch) -> None:
    from agents.planners import StraightToGoal
    from agents.training import pretrain as pretrain_module
    from envs.config import config_from

    teacher = _CountingTeacher()
    monkeypatch.setattr(pretrain_module, "make_teacher", lambda cfg, env_cfg: teacher)
    pre = PretrainConfig(episodes=2, n_envs=2, dagger_episodes=2)
    own = collect_teacher(pre, ENV, seed=0, gamma=0.99)  # the teacher drives: it is asked once per step
    assert teacher.calls > 0
    assert set(np.round(own.actions[:, 0], 3)) == {0.5, 1.0}
    calls = teacher.calls
    driver = StraightToGoal(config_from(ENV, {}))
    data = collect_teacher(pre, ENV, seed=0, gamma=0.99, driver=driver, round_=1)
    # the straight policy drove (every label is the teacher's, none the driver's) and labels came online
    assert teacher.calls > calls
    assert not np.allclose(data.actions, driver.predict(data.observations)[0])
    assert set(np.round(data.actions[:, 0], 3)) == {0.5, 1.0}


@pytest.mark.parametrize("arm", ["none", "cv"])
def test_a_true_future_teacher_acts_in_any_arm_as_in_the_oracle_arm(arm: str) -> None:
    """``teacher_predictor: oracle``: in the none or cv arm the teacher gives, step for step, the actions it gives in
    the oracle arm on the same episodes (the environment's dynamics do not depend on the arm), so one teacher labels
    every arm's states."""
    oracle = collect_teacher(PretrainConfig(episodes=3, n_envs=2), {**ENV, "predictor": "oracle"}, seed=4, gamma=0.99)
    pre = PretrainConfig(episodes=3, n_envs=2, teacher_predictor="oracle")
    data = collect_teacher(pre, {**ENV, "predictor": arm}, seed=4, gamma=0.99)
    np.testing.assert_array_equal(data.actions, oracle.actions)
    assert data.outcomes == oracle.outcomes
    assert ("forecasts" in data.observations) == (arm != "none"), "the student's observations stay its arm's"
    own = collect_teacher(PretrainConfig(episodes=3, n_envs=2), {**ENV, "predictor": arm}, seed=4, gamma=0.99)
    assert not np.array_equal(own.actions, oracle.actions), "with its arm's forecasts the teacher acts otherwise"


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"teacher_predictor": "mesrnn"}, r"'teacher_predictor' must be null .* 'oracle', got 'mesrnn'"),
        ({"teacher": "straight", "teacher_predictor": "oracle"}, r"the 'straight' teacher reads none"),
        ({"teacher": "privileged", "teacher_predictor": "oracle"}, r"the 'privileged' teacher reads none"),
    ],
)
def test_a_teacher_predictor_is_checked(settings: dict[str, Any], message: str) -> None:
    from crowdnav_mesrnn.config import ConfigError

    with pytest.raises(ConfigError, match=message):
        PretrainConfig(**settings).validate()
