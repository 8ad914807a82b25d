"""Robot motion, contacts with fault, termination, reward components and episode metrics."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from envs.config import CrowdNavConfig
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording, synthetic_recording
from envs.replay import Replay
from envs.rewards import REWARD_COMPONENTS
from envs.world import World, fault_of

STEP = 0.4


def walker(start: tuple[float, float], velocity: tuple[float, float], steps: int) -> np.ndarray:
    """``(steps, 2)`` positions at 0.4 s annotations of a pedestrian walking at a constant velocity."""
    k = np.arange(steps)[:, None]
    return np.asarray(start) + k * STEP * np.asarray(velocity)


def standing_robot(obs: Any) -> np.ndarray:
    return np.zeros(2, dtype=np.float32)


@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
def test_scripted_go_to_goal_reaches_the_goal_in_an_empty_scene(
    kinematics: str, episode_runner: Callable, goal_seeker: Callable
) -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty", kinematics=kinematics)
    cfg = env.config
    for seed in range(3):
        steps = episode_runner(env, lambda obs: goal_seeker(obs, cfg), seed=seed)
        _, _, terminated, truncated, info = steps[-1]
        metrics = info["episode_metrics"]
        assert terminated and not truncated
        assert metrics["outcome"] == "success" and info["reached_goal"]
        assert info["reward_components"]["success"] == cfg.success_reward
        assert metrics["collisions"] == 0 and metrics["min_gap_m"] is None
        straight = np.linalg.norm(np.subtract(steps[0][4]["goal"], steps[0][4]["start"]))
        if kinematics == "holonomic":
            # straight line at the preferred speed: ceil(d / 0.4 m) steps, path ratio 1
            assert metrics["steps"] == math.ceil(
                (straight - cfg.goal_tolerance_m) / (cfg.robot_pref_speed_mps * cfg.dt_s)
            )
            assert metrics["path_ratio"] == pytest.approx(1.0, abs=0.06)
        else:
            assert metrics["path_ratio"] < 1.2


def test_head_on_pedestrian_into_a_standing_robot_is_a_collision_at_the_pedestrian_fault(
    episode_runner: Callable,
) -> None:
    crowd = scripted_recording([walker((6.0, 0.0), (-1.2, 0.0), 40)], num_steps=200)
    env = CrowdNavEnv(predictor="cv", crowd=crowd)
    steps = episode_runner(env, standing_robot, seed=0, options={"t0_s": 0.0, "start": (0, 0), "goal": (-8, 0)})
    _, _, terminated, truncated, info = steps[-1]
    assert terminated and not truncated
    assert info["collision"] and info["collision_fault"] == "pedestrian"
    assert (
        info["episode_metrics"]["outcome"] == "collision" and info["episode_metrics"]["collision_fault"] == "pedestrian"
    )
    assert info["reward_components"]["collision"] == env.config.collision_penalty
    # contact when the centres are 0.6 m apart: (6 - 0.6) / 1.2 = 4.5 s, i.e. during the 12th step
    assert info["time_s"] == pytest.approx(4.8)
    np.testing.assert_allclose(env.robot_position, [0.0, 0.0], atol=1e-12)


def test_robot_walking_into_a_standing_pedestrian_is_at_fault(episode_runner: Callable) -> None:
    crowd = scripted_recording([np.tile([3.0, 0.0], (100, 1))])
    env = CrowdNavEnv(predictor="none", crowd=crowd)
    steps = episode_runner(env, lambda obs: np.array([1.0, 0.0], dtype=np.float32), seed=0,
                           options={"t0_s": 0.0, "start": (0, 0), "goal": (8, 0)})  # fmt: skip
    info = steps[-1][4]
    assert info["collision_fault"] == "robot" and info["episode_metrics"]["outcome"] == "collision"


@pytest.mark.parametrize("speed", [1.5, 2.5, 3.5])
def test_fast_pedestrians_cannot_pass_through_the_robot(speed: float, episode_runner: Callable) -> None:
    crowd = scripted_recording([walker((8.0, 0.1), (-speed, 0.0), 60)])
    env = CrowdNavEnv(predictor="none", crowd=crowd)
    steps = episode_runner(env, standing_robot, seed=0, options={"t0_s": 0.0, "start": (0, 0), "goal": (0, -8)})
    assert steps[-1][4]["episode_metrics"]["outcome"] == "collision"


def test_near_miss_gives_discomfort_not_collision(episode_runner: Callable) -> None:
    # passes 0.7 m from the robot's centre: gap 0.1 m at closest approach (annotation at x = 0)
    crowd = scripted_recording([walker((4.8, 0.7), (-1.2, 0.0), 20)])
    env = CrowdNavEnv(predictor="none", crowd=crowd, time_limit_factor=1.0)
    steps = episode_runner(env, standing_robot, seed=0, options={"t0_s": 0.0, "start": (0, 0), "goal": (0, -8)})
    infos = [s[4] for s in steps[1:]]
    assert not any(i["collision"] for i in infos)
    closest = min(infos, key=lambda i: i["min_gap_m"] if i["min_gap_m"] is not None else math.inf)
    assert closest["min_gap_m"] == pytest.approx(0.1, abs=1e-9)
    cfg = env.config
    expected = (0.1 - cfg.discomfort_dist_m) * cfg.discomfort_scale * cfg.dt_s
    assert closest["reward_components"]["discomfort"] == pytest.approx(expected, abs=1e-9)
    assert infos[-1]["episode_metrics"]["min_gap_m"] == pytest.approx(0.1, abs=1e-9)
    assert infos[-1]["episode_metrics"]["outcome"] == "timeout"


def test_episode_can_continue_after_contact(episode_runner: Callable) -> None:
    crowd = scripted_recording([walker((3.0, 0.05), (-1.0, 0.0), 30)])
    env = CrowdNavEnv(predictor="none", crowd=crowd, terminate_on_collision=False, time_limit_factor=1.0)
    steps = episode_runner(env, standing_robot, seed=0, options={"t0_s": 0.0, "start": (0, 0), "goal": (0, -8)})
    in_contact = [s[4]["collision"] for s in steps[1:]]
    # overlapping while |x| < 0.598 m, i.e. from t = 2.402 s to 3.598 s: steps 7, 8 and 9
    assert sum(in_contact) == 3
    assert all(s[4]["reward_components"]["collision"] == -20.0 for s in steps[1:] if s[4]["collision"])
    final = steps[-1][4]["episode_metrics"]
    assert final["outcome"] == "timeout" and final["collisions"] == 1 and final["collision_fault"] == "pedestrian"


def test_reward_components_sum_to_the_reward(data_dir: Path) -> None:
    env = CrowdNavEnv(
        predictor="oracle",
        data_dir=str(data_dir),
        split="univ",
        part="test",
        intrusion_penalty=-0.1,
        time_penalty=-0.01,
    )
    env.action_space.seed(3)
    env.reset(seed=3)
    seen: set[str] = set()
    total = 0.0
    for _ in range(400):
        _, reward, terminated, truncated, info = env.step(env.action_space.sample())
        comps = info["reward_components"]
        assert tuple(comps) == REWARD_COMPONENTS
        assert reward == sum(comps.values())
        assert comps["time"] == -0.01
        seen.update(k for k, v in comps.items() if v != 0.0)
        total += reward
        if terminated or truncated:
            assert info["episode_metrics"]["r"] == pytest.approx(total)
            total = 0.0
            env.reset()
    assert {"collision", "discomfort", "progress", "intrusion", "time"} <= seen


def test_progress_is_potential_based(episode_runner: Callable) -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty", progress_gamma=0.9)
    env.reset(seed=0, options={"start": (0.0, 0.0), "goal": (3.0, 4.0)})
    _, _, _, _, info = env.step(np.array([0.6, 0.8], dtype=np.float32))
    d_after = 5.0 - 0.4
    assert info["reward_components"]["progress"] == pytest.approx(5.0 - 0.9 * d_after, abs=1e-12)
    assert info["distance_to_goal_m"] == pytest.approx(d_after, abs=1e-12)


def test_unicycle_turns_and_moves() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty", kinematics="unicycle")
    obs, _ = env.reset(seed=0, options={"start": (0.0, 0.0), "goal": (5.0, 0.0)})
    np.testing.assert_allclose(obs["robot"][4:6], [1.0, 0.0], atol=1e-7)
    obs, *_ = env.step(np.array([0.0, 1.0], dtype=np.float32))  # turn in place at 2 rad/s for 0.4 s
    np.testing.assert_allclose(obs["robot"][4:6], [math.cos(0.8), math.sin(0.8)], atol=1e-6)
    np.testing.assert_allclose(env.robot_position, [0.0, 0.0], atol=1e-12)
    env.step(np.array([1.0, 0.0], dtype=np.float32))
    np.testing.assert_allclose(env.robot_position, 0.4 * np.array([math.cos(0.8), math.sin(0.8)]), atol=1e-9)


def test_fault_rule() -> None:
    right = np.array([1.0, 0.0])
    assert fault_of(np.zeros(2), -right, np.zeros(2), right)[0] == "pedestrian"
    assert fault_of(right, np.zeros(2), np.zeros(2), right)[0] == "robot"
    assert fault_of(right, -2 * right, np.zeros(2), right)[0] == "pedestrian"
    assert fault_of(np.zeros(2), np.zeros(2), np.zeros(2), right)[0] == "pedestrian"  # appeared on the robot


def test_only_pedestrians_near_the_robot_enter_pymunk(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="none", data_dir=str(data_dir), split="univ", part="test")
    env.reset(seed=0)
    for _ in range(20):
        _, _, terminated, truncated, _ = env.step(np.zeros(2, dtype=np.float32))
        if terminated or truncated:
            break
    assert env.replay.num_pedestrians > 40
    assert env.world.num_bodies < 10


def test_world_contact_needs_overlap() -> None:
    world = World(0.3, 0.3)
    world.reset(np.zeros(2))
    rows = np.array([0])
    # pedestrian passing at 0.61 m and at 0.59 m from the robot's centre
    for y, touches in ((0.61, False), (0.59, True)):
        world.reset(np.zeros(2))
        path = np.stack([np.array([[x, y]]) for x in np.linspace(2.0, -2.0, 41)])
        present = np.ones((41, 1), dtype=bool)
        result = world.step([(0.0, 0.0)] * 40, path, present, rows, 0.1)
        assert bool(result.contacts) is touches


def test_synthetic_crowd_is_deterministic_and_plausible() -> None:
    a = synthetic_recording(seed=3, duration_s=60.0)
    synthetic_recording.cache_clear()
    b = synthetic_recording(seed=3, duration_s=60.0)
    np.testing.assert_array_equal(a.positions, b.positions)
    assert a.step_s == 0.4 and a.present.sum(axis=1).mean() > 3
    r = Replay(a)
    both = r.valid[:-1]
    speeds = np.linalg.norm(r.slopes[:-1], axis=-1)[both]
    assert 0.7 < np.median(speeds) < 1.6
    cfg = CrowdNavConfig()
    assert a.positions[a.present].min() > -1.5 and a.positions[a.present, 0].max() < cfg.synthetic_area_m[0] + 1.5
