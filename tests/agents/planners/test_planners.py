"""The non-learned planners: SB3's predict interface, single and batched, and what they must achieve."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from agents.planners import (
    SamplingPlanner,
    SearchPlanner,
    StraightToGoal,
    go_to_goal,
    lattice_select,
    make_planner,
    motion_candidates,
)
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
@pytest.mark.parametrize("name", ["straight", "planner", "search"])
def test_planners_reach_the_goal_in_an_empty_scene(name: str, kinematics: str) -> None:
    env = CrowdNavEnv(predictor="cv", crowd="empty", kinematics=kinematics)
    for seed in range(3):
        assert run(env, make_planner(name, env.config), seed=seed)["outcome"] == "success"


@pytest.mark.parametrize("predictor", ["none", "cv"])
@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
def test_batched_predict_equals_single_predicts(predictor: str, kinematics: str) -> None:
    env = CrowdNavEnv(predictor=predictor, crowd="synthetic", kinematics=kinematics)
    policies = [make_planner("planner", env.config), make_planner("straight", env.config)]
    policies += [make_planner("search", env.config), make_planner("planner", env.config, candidates="dense")]
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
    dense = SamplingPlanner(env.config, candidates="dense")
    assert dense.num_candidates == 16 * 6 + 1 and np.isclose(np.abs(dense._angles).max(), np.pi)  # backs away
    with pytest.raises(ValueError, match="unknown candidates 'wide'; valid: default, dense"):
        SamplingPlanner(env.config, candidates="wide")
    assert SearchPlanner(env.config).num_candidates == 16 * 3 + 3 + 1
    for bad in ({"lookahead_steps": 0}, {"margin_m": -0.1}, {"cell_m": 0.0}, {"max_states": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SearchPlanner(env.config, **bad)
    with pytest.raises(ValueError, match="unknown planner"):
        make_planner("ppo", env.config)
    with pytest.raises(ValueError, match="'robot' and 'mask'"):
        planner.predict({"robot": obs["robot"]})


def test_make_planner_accepts_a_mapping_config() -> None:
    planner = make_planner("planner", {"kinematics": "unicycle", "num_pedestrians": 5})
    assert planner.cfg.kinematics == "unicycle" and planner.cfg.num_pedestrians == 5


def front_crowd(width: int = 5, speed_mps: float = 1.2) -> Any:
    """``width`` pedestrians side by side (1 m apart, gaps narrower than the robot) walking along -x at ``speed_mps``,
    their front at x = 3 m at t = 3.2 s: faster than the robot, too wide to sidestep before they arrive."""
    ys = np.linspace(-(width - 1) / 2, (width - 1) / 2, width)
    return scripted_recording([[(3.0 + speed_mps * 0.4 * (8 - k), y) for k in range(80)] for y in ys])


@pytest.mark.parametrize("predictor", ["none", "cv", "oracle"])
def test_search_planner_backs_away_from_a_front_it_cannot_sidestep(predictor: str) -> None:
    env = CrowdNavEnv(predictor=predictor, crowd=front_crowd())
    assert run(env, StraightToGoal(env.config), options=HEAD_ON)["outcome"] == "collision"
    assert run(env, SamplingPlanner(env.config), options=HEAD_ON)["outcome"] == "collision"  # never backs away
    obs, _ = env.reset(seed=0, options=HEAD_ON)
    planner, backed, done, info = SearchPlanner(env.config), False, False, {}
    while not done:
        action = planner.predict(obs)[0]
        backed |= bool(action[0] < -0.1)  # a velocity away from the goal (+x)
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    assert info["episode_metrics"]["outcome"] == "success" and backed


def test_motion_candidates_cover_headings_speeds_goal_and_standing() -> None:
    headings, fractions = np.deg2rad([0.0, 90.0, 180.0]), np.array([1.0, 0.5])
    states = np.array([[0.0, 0.0], [9.8, 0.0]])
    vel = motion_candidates(states, np.array([10.0, 0.0]), np.zeros(2), 1.0, 0.4, headings, fractions)
    assert vel.shape == (2, 3 * 2 + 2 + 1, 2)
    np.testing.assert_allclose(vel[0, :6], [[1, 0], [0.5, 0], [0, 1], [0, 0.5], [-1, 0], [-0.5, 0]], atol=1e-12)
    np.testing.assert_allclose(vel[0, 6:8], [[1, 0], [0.5, 0]])  # towards the goal, 10 m away: full speed
    np.testing.assert_allclose(vel[1, 6:8], [[0.5, 0], [0.25, 0]])  # 0.2 m away: the first arrives in one step
    np.testing.assert_array_equal(vel[:, -1], 0.0)


def test_lattice_select_keeps_one_per_cell_then_the_nearest_per_group() -> None:
    rng = np.random.default_rng(0)
    group = rng.integers(0, 3, 400)
    points = rng.uniform(-1, 1, (400, 2))
    prefer, rank = rng.integers(0, 50, 400), rng.random(400)
    kept = lattice_select(group, points, prefer, rank, 0.25, keep=5)
    # the same with loops and dicts
    best: dict[tuple[int, int, int], int] = {}
    for i in range(400):
        key = (int(group[i]), *np.floor(points[i] / 0.25).astype(int).tolist())
        if key not in best or prefer[i] < prefer[best[key]]:
            best[key] = i
    expected = []
    for g in range(3):
        members = sorted((i for k, i in best.items() if k[0] == g), key=lambda i: rank[i])
        expected += members[:5]
    assert kept.tolist() == expected


def test_search_gaps_are_the_closest_approach_of_the_two_motions() -> None:
    rng = np.random.default_rng(1)
    planner = SearchPlanner({"num_pedestrians": 4})
    b, m, a, k = 2, 3, 5, 4
    x = rng.uniform(-1, 1, (b, m, 2))
    move = rng.uniform(-0.4, 0.4, (b, m, a, 2))
    q0, q1 = rng.uniform(-1.5, 1.5, (b, k, 2)), rng.uniform(-1.5, 1.5, (b, k, 2))
    mask = rng.random((b, k)) < 0.8
    grow = rng.uniform(0.0, 0.3, (b, k))
    gaps = planner._gaps(x, np.ones((b, m), dtype=bool), move, q0, q1, mask, grow)
    t = np.linspace(0.0, 1.0, 20001)[:, None]
    for i, j, c in np.ndindex(b, m, a):
        robot = x[i, j] + t * move[i, j, c]
        dense = min(
            (
                np.hypot(*(robot - (q0[i, n] + t * (q1[i, n] - q0[i, n]))).T).min() - grow[i, n]
                for n in range(k)
                if mask[i, n]
            ),
            default=np.inf,
        )
        if dense - planner.r_sum < planner.far_m - planner.r_sum:  # pairs farther apart may be left uncomputed
            assert gaps[i, j, c] == pytest.approx(dense - planner.r_sum, abs=1e-6)
        else:
            assert gaps[i, j, c] >= planner.far_m - planner.r_sum - 1e-9
