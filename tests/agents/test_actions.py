"""The discrete goal-relative action set: geometry, labelling a teacher, the wrapper and the policy adapter."""

from __future__ import annotations

import numpy as np
import pytest

from agents.actions import DiscreteActionWrapper, DiscretePolicy, GoalRelativeActions, make_actions
from agents.planners import SamplingPlanner
from crowdnav_mesrnn.config import ConfigError
from envs.config import CrowdNavConfig
from envs.crowd_nav import CrowdNavEnv


def _robot(goal_offset: tuple[float, float]) -> np.ndarray:
    return np.array([[goal_offset[0], goal_offset[1], 0.0, 0.0]], dtype=np.float32)


def test_action_zero_heads_at_the_goal_at_full_speed_and_the_last_stands_still() -> None:
    cfg = CrowdNavConfig()
    acts = GoalRelativeActions(cfg, headings_deg=(0.0, 90.0), speed_fractions=(1.0, 0.5))
    assert acts.n == 5
    vel = acts.velocities(_robot((0.0, 5.0)))[0]
    np.testing.assert_allclose(vel[0], [0.0, cfg.robot_pref_speed_mps], atol=1e-12)  # towards +y at full speed
    np.testing.assert_allclose(vel[1], [0.0, 0.5 * cfg.robot_pref_speed_mps], atol=1e-12)
    np.testing.assert_allclose(vel[2], [-cfg.robot_pref_speed_mps, 0.0], atol=1e-12)  # 90 deg to the left of +y
    np.testing.assert_allclose(vel[4], [0.0, 0.0])


def test_speed_is_capped_to_arrive_in_one_step() -> None:
    cfg = CrowdNavConfig(dt_s=0.4)
    acts = GoalRelativeActions(cfg)
    vel = acts.velocities(_robot((0.2, 0.0)))[0]
    assert np.hypot(*vel[0]) == pytest.approx(0.2 / 0.4)  # reaches the goal in one step


def test_teacher_labels_round_trip_exactly_for_the_sampling_planner(data_dir) -> None:
    env = CrowdNavEnv(predictor="none", split="zara1", part="test")
    acts = GoalRelativeActions(env.config)
    planner = SamplingPlanner(env.config)
    checked = 0
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            a = planner.predict(obs)[0]
            index = acts.nearest(a[None], obs["robot"][None])
            np.testing.assert_allclose(acts.to_env_actions(index, obs["robot"][None])[0], a, atol=1e-6)
            obs, _, terminated, truncated, _ = env.step(a)
            done = terminated or truncated
            checked += 1
    assert checked > 20


def test_wrapper_steps_the_env_with_the_mapped_velocity() -> None:
    env = DiscreteActionWrapper(CrowdNavEnv(predictor="none", crowd="empty"), GoalRelativeActions(CrowdNavConfig()))
    assert env.action_space.n == 57
    obs, _ = env.reset(seed=0)
    before = np.asarray(obs["robot"][:2], dtype=np.float64).copy()
    obs, *_ = env.step(0)  # straight at the goal at full speed
    after = np.asarray(obs["robot"][:2], dtype=np.float64)
    assert np.hypot(*before) - np.hypot(*after) == pytest.approx(0.4, abs=1e-3)
    with pytest.raises(ValueError, match="discrete action"):
        env.step(57)


class _FixedModel:
    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        n = 1 if np.ndim(obs["mask"]) == 1 else len(obs["mask"])
        return np.full(n, 56), state


def test_policy_adapter_returns_env_actions_for_single_and_batched_observations() -> None:
    acts = GoalRelativeActions(CrowdNavConfig())
    policy = DiscretePolicy(_FixedModel(), acts)
    obs = {"robot": _robot((3.0, 4.0))[0], "mask": np.zeros(10, dtype=np.int8)}
    np.testing.assert_array_equal(policy.predict(obs)[0], [0.0, 0.0])
    batch = {k: np.stack([v, v, v]) for k, v in obs.items()}
    assert policy.predict(batch)[0].shape == (3, 2)


def test_bad_options_name_the_key() -> None:
    with pytest.raises(ConfigError, match="holonomic"):
        GoalRelativeActions(CrowdNavConfig(kinematics="unicycle"))
    with pytest.raises(ConfigError, match="speed_fractions"):
        make_actions(CrowdNavConfig(), {"speed_fractions": [0.0, 1.0]})
    with pytest.raises(ConfigError, match="unknown action key"):
        make_actions(CrowdNavConfig(), {"speeds": [1.0]})
