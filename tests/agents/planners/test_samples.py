"""The search planner's ``samples`` option: each pedestrian is its sampled futures, and a plan must keep clear of at
least ``sample_share`` of them at every step (a chance constraint)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agents.planners import SearchPlanner, StraightToGoal
from envs.config import config_from
from envs.crowd_nav import CrowdNavEnv
from tests.agents.planners.test_uncertainty import observation as region_observation

CFG = config_from({"num_pedestrians": 2, "horizon_steps": 12, "flatten_observation": False, "forecast_samples": 10}, {})


def observation(now_y: float, sample_y: list[float], from_step: int = 0) -> dict[str, np.ndarray]:
    """The region tests' scene (:func:`tests.agents.planners.test_uncertainty.observation`: robot at rest, goal 10 m
    ahead on x) with its pedestrian at (2, ``now_y``), forecast to stay there, and samples standing at
    (2, ``sample_y[s]``) from look-ahead step ``from_step`` on."""
    obs = region_observation(0.0)
    del obs["forecast_uncertainty"]
    obs["forecasts"][0] = (2.0, now_y)
    obs["pedestrians"][0, :2] = (2.0, now_y)
    samples = np.zeros((2, len(sample_y), 12, 2), np.float32)
    samples[0] = (2.0, now_y)
    samples[0, :, from_step:, 1] = np.asarray(sample_y, np.float32)[:, None]
    obs["forecast_samples"] = samples
    return obs


def test_samples_all_on_the_point_forecast_give_the_point_planners_choice() -> None:
    obs = observation(0.0, [0.0] * 10)  # someone standing on the straight path
    point = SearchPlanner(CFG).predict(obs)[0]
    assert not np.allclose(point, [1.0, 0.0])  # the point planner goes around
    np.testing.assert_array_equal(SearchPlanner(CFG, samples=True).predict(obs)[0], point)


def test_with_share_0_it_keeps_clear_of_nothing() -> None:
    obs = observation(0.0, [0.0] * 10)
    straight = StraightToGoal(CFG).predict(obs)[0]
    np.testing.assert_array_equal(SearchPlanner(CFG, samples=True, sample_share=0.0).predict(obs)[0], straight)


@pytest.mark.parametrize(("blocking", "share", "goes_straight"), [(1, 0.9, True), (1, 1.0, False), (2, 0.9, False)])
def test_a_plan_must_clear_the_declared_share_of_the_samples(blocking: int, share: float, goes_straight: bool) -> None:
    """The pedestrian stands 3 m off the path; ``blocking`` of its 10 samples step onto the path from step 3 on. The
    straight plan clears 9 of 10 with one blocking: admissible at share 0.9, not at 1.0 nor with two blocking."""
    obs = observation(3.0, [0.0] * blocking + [3.0] * (10 - blocking), from_step=2)
    action = SearchPlanner(CFG, samples=True, sample_share=share).predict(obs)[0]
    assert np.allclose(action, [1.0, 0.0]) == goes_straight, action


def test_options_and_the_key_are_checked() -> None:
    obs = observation(0.0, [0.0] * 10)
    del obs["forecast_samples"]
    with pytest.raises(ValueError, match="forecast_samples=S"):
        SearchPlanner(CFG, samples=True).predict(obs)
    with pytest.raises(ValueError, match="choose one"):
        SearchPlanner(CFG, samples=True, uncertainty=True)
    with pytest.raises(ValueError, match="sample_share"):
        SearchPlanner(CFG, samples=True, sample_share=1.5)


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
def test_on_replayed_scenes_equal_samples_give_the_point_plans_and_runs_repeat(data_dir: Path) -> None:
    """Observations of a cv_gaussian episode (batched): with every sample replaced by the forecast the samples planner
    chooses as the point planner does; with the drawn samples, the same episode twice gives the same actions."""

    def rollout() -> tuple[list[np.ndarray], list[dict[str, np.ndarray]]]:
        env = CrowdNavEnv(predictor="cv_gaussian", split="zara1", part="test", forecast_samples=20)
        planner = SearchPlanner(env.config, samples=True)
        obs, _ = env.reset(seed=4)
        actions, seen = [], []
        for _ in range(25):
            action = planner.predict(obs)[0]
            actions.append(action)
            seen.append(obs)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
        return actions, seen

    actions, seen = rollout()
    again, _ = rollout()
    np.testing.assert_array_equal(np.stack(actions), np.stack(again))
    cfg = config_from({"forecast_samples": 20}, {})
    batch = {k: np.stack([o[k] for o in seen]) for k in seen[0]}
    on_point = dict(batch)
    fc = batch["forecasts"].reshape(len(seen), 10, 1, 12, 2)
    on_point["forecast_samples"] = np.broadcast_to(fc, (len(seen), 10, 20, 12, 2)).reshape(len(seen), -1)
    assert batch["mask"].any(axis=1).sum() > 5
    np.testing.assert_array_equal(
        SearchPlanner(cfg, samples=True).predict(on_point)[0], SearchPlanner(cfg).predict(batch)[0]
    )
