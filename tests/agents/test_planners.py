"""The non-learned planners: SB3's predict interface, single and batched, and what they must achieve."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from agents.planners import SamplingPlanner, StraightToGoal, go_to_goal, make_planner
from envs.crowd_nav import CrowdNavEnv
from envs.crowds import scripted_recording


def head_on_crowd() -> Any:
    """One pedestrian walking along y = 0 towards -x at 1.2 m/s (annotations every 0.4 s)."""
    return scripted_recording([[(14.0 - 0.48 * k, 0.0) for k in range(60)]])


def run(env: CrowdNavEnv, policy: Any, seed: int = 0, options: dict | None = None) -> dict:
    obs, _ = env.reset(seed=seed, options=options)
    done, info = False, {}
    while not done:
        action, state = policy.predict(obs, deterministic=True)
        assert state is None and action.shape == (2,) and action.dtype == np.float32
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return info["episode_metrics"]


HEAD_ON = {"t0_s": 3.2, "start": (0.0, 0.0), "goal": (10.0, 0.0)}


@pytest.mark.parametrize("predictor", ["none", "cv", "oracle"])
def test_sampling_planner_avoids_a_head_on_pedestrian_that_straight_to_goal_hits(predictor: str) -> None:
    env = CrowdNavEnv(predictor=predictor, crowd=head_on_crowd())
    assert run(env, StraightToGoal(env.config), options=HEAD_ON)["outcome"] == "collision"
    assert run(env, SamplingPlanner(env.config), options=HEAD_ON)["outcome"] == "success"


@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
@pytest.mark.parametrize("name", ["straight", "planner"])
def test_planners_reach_the_goal_in_an_empty_scene(name: str, kinematics: str) -> None:
    env = CrowdNavEnv(predictor="cv", crowd="empty", kinematics=kinematics)
    for seed in range(3):
        assert run(env, make_planner(name, env.config), seed=seed)["outcome"] == "success"


@pytest.mark.parametrize("predictor", ["none", "cv"])
@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
def test_batched_predict_equals_single_predicts(predictor: str, kinematics: str) -> None:
    env = CrowdNavEnv(predictor=predictor, crowd="synthetic", kinematics=kinematics)
    policies = [make_planner("planner", env.config), make_planner("straight", env.config)]
    observations = []
    for seed in range(4):
        obs, _ = env.reset(seed=seed)
        for _ in range(12):
            observations.append(obs)
            obs, _, terminated, truncated, _ = env.step(policies[0].predict(obs)[0])
            if terminated or truncated:
                break
    batch = {k: np.stack([o[k] for o in observations]) for k in observations[0]}
    for policy in policies:
        actions, state = policy.predict(batch, state=None, episode_start=np.ones(len(observations)))
        assert state is None and actions.shape == (len(observations), 2) and actions.dtype == np.float32
        singles = np.stack([policy.predict(o)[0] for o in observations])
        np.testing.assert_array_equal(actions, singles)
        assert np.all(np.abs(actions) <= 1.0)


def test_go_to_goal_is_the_straight_policy_and_heads_at_the_goal() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty")
    obs, _ = env.reset(seed=0)
    action = go_to_goal(obs, env.config)
    np.testing.assert_array_equal(action, StraightToGoal(env.config).predict(obs)[0])
    goal_dir = obs["robot"][:2] / np.linalg.norm(obs["robot"][:2])
    np.testing.assert_allclose(action, goal_dir, atol=1e-6)


def test_candidate_set_is_configurable_and_validated() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty")
    assert SamplingPlanner(env.config).num_candidates == 37
    planner = SamplingPlanner(env.config, headings_deg=np.arange(-90, 91, 15), speed_fractions=(1.0, 0.75, 0.5, 0.25))
    assert planner.num_candidates == 13 * 4 + 1
    obs, _ = env.reset(seed=0)
    assert planner.predict(obs)[0].shape == (2,)
    with pytest.raises(ValueError, match="speed_fractions"):
        SamplingPlanner(env.config, speed_fractions=(0.0,))
    with pytest.raises(ValueError, match="unknown planner"):
        make_planner("ppo", env.config)
    with pytest.raises(ValueError, match="'robot' and 'mask'"):
        planner.predict({"robot": obs["robot"]})


def test_make_planner_accepts_a_mapping_config() -> None:
    planner = make_planner("planner", {"kinematics": "unicycle", "num_pedestrians": 5})
    assert planner.cfg.kinematics == "unicycle" and planner.cfg.num_pedestrians == 5
