"""The episode metrics reviewers ask for (issue 31): time to collision, SPL, the path ratio to the distance
required, speed and acceleration -- against closed forms, a brute-force loop and scripted episodes."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import pytest

from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording
from envs.rewards import METRIC_LABELS, EpisodeMetrics, metric_label, min_time_to_collision, time_to_collision

STEP = 0.4  # seconds between the scripted annotations
R_SUM = 0.6  # robot radius 0.3 m + pedestrian radius 0.3 m (the defaults)


def brute_force_ttc(p: np.ndarray, v: np.ndarray, r: float, horizon_s: float = 60.0, dt: float = 1e-4) -> float:
    """The first time on a fine grid at which the centres are within ``r`` (inf within the horizon: never)."""
    t = np.arange(0.0, horizon_s, dt)
    d = np.hypot(p[0] + v[0] * t, p[1] + v[1] * t)
    hit = np.flatnonzero(d <= r)
    return float(t[hit[0]]) if hit.size else math.inf


def test_head_on_approach_is_the_gap_over_the_closing_speed() -> None:
    for d, s in ((5.0, 1.2), (2.0, 0.5), (10.0, 2.4)):
        t = time_to_collision(np.array([[d, 0.0]]), np.array([[-s, 0.0]]), R_SUM)
        assert t[0] == pytest.approx((d - R_SUM) / s, abs=1e-12)


@pytest.mark.parametrize(
    ("p", "v", "expected"),
    [
        ((3.0, 0.0), (1.0, 0.0), math.inf),  # moving apart
        ((3.0, 0.0), (0.0, 0.0), math.inf),  # at rest relative to each other
        ((3.0, 1.0), (-1.0, 0.0), math.inf),  # passing 1 m wide of a 0.6 m contact distance
        ((0.3, 0.0), (1.0, 0.0), 0.0),  # overlapping already (even when separating)
        ((0.6, 0.0), (-1.0, 0.0), 0.0),  # touching
    ],
)
def test_disks_that_never_touch_or_already_touch(p: tuple, v: tuple, expected: float) -> None:
    assert time_to_collision(np.array([p]), np.array([v]), R_SUM)[0] == expected


def test_oblique_approaches_match_a_brute_force_loop() -> None:
    rng = np.random.default_rng(3)
    p = rng.uniform(-5, 5, size=(40, 2))
    v = rng.uniform(-2, 2, size=(40, 2))
    got = time_to_collision(p, v, R_SUM)
    for k in range(len(p)):
        want = brute_force_ttc(p[k], v[k], R_SUM)
        if math.isinf(want):
            # never within the horizon: no touch, or one so far off it is beyond it
            assert math.isinf(got[k]) or got[k] > 59.0
        else:
            assert got[k] == pytest.approx(want, abs=2e-4)


def test_min_time_to_collision_reads_present_pedestrians_only() -> None:
    positions = np.array([[2.0, 0.0], [5.0, 0.0]])
    velocities = np.array([[-1.0, 0.0], [-1.0, 0.0]])
    both = min_time_to_collision(np.zeros(2), np.zeros(2), positions, velocities, np.array([True, True]), R_SUM)
    far = min_time_to_collision(np.zeros(2), np.zeros(2), positions, velocities, np.array([False, True]), R_SUM)
    assert both == pytest.approx(1.4) and far == pytest.approx(4.4)
    # the robot's own velocity counts: walking towards the far one at 1 m/s doubles the closing speed
    toward = min_time_to_collision(np.zeros(2), np.array([1.0, 0.0]), positions, velocities, np.array([0, 1]), R_SUM)
    assert toward == pytest.approx(2.2)
    assert min_time_to_collision(np.zeros(2), np.zeros(2), positions, velocities, np.zeros(2, bool), R_SUM) == math.inf


def _metrics(path: list[tuple[float, float]], outcome: str, tolerance: float = 0.3) -> dict:
    m = EpisodeMetrics(np.array(path[0]), np.array([10.0, 0.0]), 0.5, 0.25, goal_tolerance_m=tolerance)
    for a, b in itertools.pairwise(path):
        v = (np.subtract(b, a)) / 0.5
        m.update(0.0, float(np.hypot(*np.subtract(b, a))), v, math.inf, False, 0, None)
    return m.summary(outcome, 0.5 * (len(path) - 1), False)


def test_spl_and_the_path_ratio_to_the_distance_required_by_hand() -> None:
    # a detour: up 3 m, then to 0.3 m short of the goal at (10, 0): 3 + hypot(9.7, 3) metres
    detour = [(0.0, 0.0), (0.0, 3.0), (9.7, 0.0)]
    path = 3.0 + math.hypot(9.7, 3.0)
    s = _metrics(detour, "success")
    assert s["path_length_m"] == pytest.approx(path)
    assert s["path_ratio"] == pytest.approx(path / 10.0)
    assert s["path_ratio_required"] == pytest.approx(path / 9.7)
    assert s["spl"] == pytest.approx(9.7 / path)
    # straight to the edge of the tolerance: the old ratio says 0.97 (shorter than the straight line), the new 1
    straight = _metrics([(0.0, 0.0), (4.85, 0.0), (9.7, 0.0)], "success")
    assert straight["path_ratio"] == pytest.approx(0.97) and straight["path_ratio_required"] == pytest.approx(1.0)
    assert straight["spl"] == pytest.approx(1.0)
    # a failure scores 0 whatever its path
    assert _metrics(detour, "collision")["spl"] == 0.0 and _metrics(detour, "timeout")["spl"] == 0.0


def test_speed_and_acceleration_by_hand() -> None:
    # from rest: 1 m/s for two steps, then 2 m/s (dt 0.5 s): |dv| = 1, 0, 1 -> accelerations 2, 0, 2 m/s^2
    s = _metrics([(0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (2.0, 0.0)], "timeout")
    assert s["mean_speed_mps"] == pytest.approx(2.0 / 1.5)
    assert s["mean_accel_mps2"] == pytest.approx(4.0 / 3.0)


def test_every_metric_has_a_label_naming_its_key() -> None:
    s = _metrics([(0.0, 0.0), (9.7, 0.0)], "success")
    assert set(s) <= set(METRIC_LABELS)
    assert metric_label("spl").startswith("spl (") and metric_label("unknown_key") == "unknown_key"


def walker(start: tuple[float, float], velocity: tuple[float, float], steps: int) -> np.ndarray:
    k = np.arange(steps)[:, None]
    return np.asarray(start) + k * STEP * np.asarray(velocity)


def standing(_obs: object) -> np.ndarray:
    return np.zeros(2, dtype=np.float32)


def test_an_approaching_pedestrian_gives_the_closed_form_ttc_in_an_episode(episode_runner: Callable) -> None:
    """Head-on at 1.2 m/s from 6 m at a standing robot, the episode cut after 5 steps (2 s): at its last step the
    pedestrian is 6 - 2.4 = 3.6 m away, so the smallest time to collision is (3.6 - 0.6) / 1.2 = 2.5 s."""
    crowd = scripted_recording([walker((6.0, 0.0), (-1.2, 0.0), 40)], num_steps=200)
    env = CrowdNavEnv(predictor="none", crowd=crowd)
    opts = {"t0_s": 0.0, "start": (0, 0), "goal": (-8, 0), "time_limit_s": 2.0}
    steps = episode_runner(env, standing, seed=0, options=opts)
    final = steps[-1][4]["episode_metrics"]
    assert final["outcome"] == "timeout" and final["steps"] == 5
    assert final["min_ttc_s"] == pytest.approx(2.5, abs=1e-9)
    # ... and when the episode runs into the collision: 0 at contact
    steps = episode_runner(env, standing, seed=0, options={**opts, "time_limit_s": 20.0})
    final = steps[-1][4]["episode_metrics"]
    assert final["outcome"] == "collision" and final["min_ttc_s"] == 0.0
    assert final["min_gap_m"] < 0 and final["min_clearance_m"] == 0.0  # overlap depth vs distance


def test_a_pedestrian_passing_wide_is_never_on_a_collision_course(episode_runner: Callable) -> None:
    # passes 0.7 m from the robot's centre (0.1 m outside contact): never on a collision course
    crowd = scripted_recording([walker((4.8, 0.7), (-1.2, 0.0), 20)])
    env = CrowdNavEnv(predictor="none", crowd=crowd, time_limit_factor=1.0)
    steps = episode_runner(env, standing, seed=0, options={"t0_s": 0.0, "start": (0, 0), "goal": (0, -8)})
    final = steps[-1][4]["episode_metrics"]
    assert final["min_ttc_s"] is None and final["min_gap_m"] == pytest.approx(0.1, abs=1e-9)
    assert final["min_clearance_m"] == pytest.approx(0.1, abs=1e-9)


def test_straight_to_the_goal_in_an_empty_scene_scores_spl_1(episode_runner: Callable, goal_seeker: Callable) -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty")
    cfg = env.config
    for seed in range(3):
        steps = episode_runner(env, lambda obs: goal_seeker(obs, cfg), seed=seed)
        final = steps[-1][4]["episode_metrics"]
        assert final["outcome"] == "success"
        # it stops within the tolerance, up to one step short of it: 1 <= ratio, SPL = 1 / ratio
        assert 1.0 - 1e-9 <= final["path_ratio_required"] < 1.0 + cfg.dt_s / 5
        assert final["spl"] == pytest.approx(1.0 / final["path_ratio_required"])
        assert final["min_ttc_s"] is None and final["mean_speed_mps"] <= cfg.robot_pref_speed_mps + 1e-9


def test_the_environment_page_names_every_metric_key() -> None:
    """docs/env.md maps the field's metrics to the project's keys: every key of the episode metrics is on it."""
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "env.md").read_text(encoding="utf-8")
    section = page[page.index("## Episode metrics") : page.index("## Episodes for agents")]
    keys = _metrics([(0.0, 0.0), (9.7, 0.0)], "success")
    missing = [k for k in keys if f"`{k}`" not in section]
    assert not missing, f"docs/env.md, Episode metrics, does not name {missing}"
