"""The sampling planner's ``uncertainty`` option: clearance of the forecast's uncertainty region, not its point."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agents.planners import SamplingPlanner
from envs.config import config_from
from envs.crowd_nav import CrowdNavEnv

CFG = config_from({"num_pedestrians": 2, "horizon_steps": 12, "flatten_observation": False}, {})


def observation(radius_m: float) -> dict[str, np.ndarray]:
    """Robot at rest, goal 10 m ahead on x; one pedestrian standing 1.3 m beside the straight path at x = 2 m."""
    fc = np.zeros((2, 12, 2), np.float32)
    fc[0] = (2.0, 1.3)
    peds = np.zeros((2, 4), np.float32)
    peds[0, :2] = (2.0, 1.3)
    unc = np.zeros((2, 12), np.float32)
    unc[0] = radius_m
    return {
        "robot": np.array([10.0, 0.0, 0.0, 0.0], np.float32),
        "pedestrians": peds,
        "mask": np.array([1, 0], np.int8),
        "forecasts": fc,
        "forecast_uncertainty": unc,
    }


def test_a_path_clear_of_the_point_but_not_of_the_region_is_avoided() -> None:
    point = SamplingPlanner(CFG)
    region = SamplingPlanner(CFG, uncertainty=True)
    straight = np.array([1.0, 0.0], np.float32)
    # 1.3 m from the forecast point clears the 0.8 m needed (radii + margin): both go straight when the region is 0
    np.testing.assert_allclose(point.predict(observation(1.0))[0], straight, atol=1e-6)
    np.testing.assert_allclose(region.predict(observation(0.0))[0], straight, atol=1e-6)
    # a 1 m region leaves 0.3 m: the planner with the option turns away from the pedestrian (y < 0) or slows down
    action = region.predict(observation(1.0))[0]
    assert not np.allclose(action, straight)
    velocity = action * CFG.robot_pref_speed_mps
    path = velocity[None, :] * (CFG.dt_s * np.arange(1, 7))[:, None]
    assert np.min(np.hypot(path[:, 0] - 2.0, path[:, 1] - 1.3)) - 1.0 >= region.clear_m - 1e-9


def test_the_option_needs_the_key() -> None:
    obs = observation(1.0)
    del obs["forecast_uncertainty"]
    with pytest.raises(ValueError, match="forecast_uncertainty=True"):
        SamplingPlanner(CFG, uncertainty=True).predict(obs)


def test_with_zero_radii_the_option_changes_nothing_in_an_episode(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="oracle", split="zara1", part="test", forecast_uncertainty=True)
    plain, region = SamplingPlanner(env.config), SamplingPlanner(env.config, uncertainty=True)
    obs, _ = env.reset(seed=3)
    for _ in range(15):
        action = plain.predict(obs)[0]
        np.testing.assert_array_equal(action, region.predict(obs)[0])
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break


def test_a_cv_episode_with_regions_runs(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="cv", split="zara1", part="test", forecast_uncertainty=True)
    planner = SamplingPlanner(env.config, uncertainty=True)
    obs, _ = env.reset(seed=0)
    done, info = False, {}
    while not done:
        obs, _, terminated, truncated, info = env.step(planner.predict(obs)[0])
        done = terminated or truncated
    assert info["episode_metrics"]["outcome"] in ("success", "collision", "timeout")
