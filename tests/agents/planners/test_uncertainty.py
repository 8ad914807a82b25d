"""The planners' ``uncertainty`` option (sampling and search): clearance of the forecast's uncertainty region, not its
point."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from agents.planners import SamplingPlanner, SearchPlanner
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


def region_action(planner: type) -> np.ndarray:
    """The action of ``planner`` with the option when the pedestrian's region is 1 m wide, after checking that the
    point (and a zero region) leaves the straight path clear: 1.3 m from the forecast point clears the 0.8 m the
    sampling planner needs (radii + margin) and the 0.6 m + margin the search planner needs."""
    straight = np.array([1.0, 0.0], np.float32)
    np.testing.assert_allclose(planner(CFG).predict(observation(1.0))[0], straight, atol=1e-6)
    region = planner(CFG, uncertainty=True)
    np.testing.assert_allclose(region.predict(observation(0.0))[0], straight, atol=1e-6)
    action = region.predict(observation(1.0))[0]
    assert not np.allclose(action, straight, atol=1e-3), action
    return action


def test_a_path_clear_of_the_point_but_not_of_the_region_is_avoided() -> None:
    # a 1 m region leaves 0.3 m: the planner with the option turns away from the pedestrian (y < 0) or slows down
    action = region_action(SamplingPlanner)
    velocity = action * CFG.robot_pref_speed_mps
    path = velocity[None, :] * (CFG.dt_s * np.arange(1, 7))[:, None]
    clear_m = SamplingPlanner(CFG).clear_m
    assert np.min(np.hypot(path[:, 0] - 2.0, path[:, 1] - 1.3)) - 1.0 >= clear_m - 1e-9


@pytest.mark.parametrize("planner", [SamplingPlanner, SearchPlanner])
def test_the_option_needs_the_key(planner: type) -> None:
    obs = observation(1.0)
    del obs["forecast_uncertainty"]
    with pytest.raises(ValueError, match="forecast_uncertainty=True"):
        planner(CFG, uncertainty=True).predict(obs)


def test_the_search_planner_plans_around_a_region_its_point_forecast_clears() -> None:
    # a 1 m region leaves -0.3 m on the straight line past x = 2 m: the plan turns away from the pedestrian (y > 0)
    action = region_action(SearchPlanner)
    assert action[1] < 0, action
    # the region is 0 at the observed position and 1 m from the first step on: every step's disk grows by 1 m,
    # so the search equals the point search with a pedestrian 1 m larger (an independent construction)
    bigger = SearchPlanner(dataclasses.replace(CFG, pedestrian_radius_m=CFG.pedestrian_radius_m + 1.0))
    np.testing.assert_array_equal(action, bigger.predict(observation(1.0))[0])


def test_the_search_planners_step_inflation_is_the_larger_radius_of_each_steps_ends() -> None:
    obs = observation(0.0)
    obs["forecast_uncertainty"][0] = np.arange(1, 13) * 0.1
    grow = SearchPlanner(CFG, uncertainty=True, lookahead_steps=4).step_inflation({k: v[None] for k, v in obs.items()})
    np.testing.assert_allclose(grow[0, 0], [0.1, 0.2, 0.3, 0.4])
    np.testing.assert_array_equal(grow[0, 1], 0.0)
    assert not SearchPlanner(CFG, lookahead_steps=4).step_inflation({k: v[None] for k, v in obs.items()}).any()


@pytest.mark.parametrize("planner", [SamplingPlanner, SearchPlanner])
def test_uncertainty_batches_like_single_predicts_and_zero_radii_change_nothing(planner: type) -> None:
    env = CrowdNavEnv(predictor="cv", crowd="synthetic", flatten_observation=False)
    rng = np.random.default_rng(0)
    observations = []
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        for _ in range(6):
            observations.append(obs)
            obs, _, terminated, truncated, _ = env.step(SamplingPlanner(env.config).predict(obs)[0])
            if terminated or truncated:
                break
    batch = {k: np.stack([o[k] for o in observations]) for k in observations[0]}
    k, h = batch["mask"].shape[1], env.config.horizon_steps
    plain, region = planner(env.config), planner(env.config, uncertainty=True)
    zero = {**batch, "forecast_uncertainty": np.zeros((len(observations), k, h), np.float32)}
    np.testing.assert_array_equal(region.predict(zero)[0], plain.predict(batch)[0])
    radii = np.cumsum(rng.uniform(0.0, 0.3, (len(observations), k, h)), axis=2).astype(np.float32)
    wide = {**batch, "forecast_uncertainty": radii}
    actions = region.predict(wide)[0]
    singles = np.stack([region.predict({key: v[i] for key, v in wide.items()})[0] for i in range(len(observations))])
    np.testing.assert_array_equal(actions, singles)
    assert not np.array_equal(actions, plain.predict(batch)[0]), "regions up to 3.6 m wide never changed an action"


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
