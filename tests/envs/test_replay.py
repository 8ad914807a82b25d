"""The replay against the files: positions at annotation times, interpolation, causal velocities, episodes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.data import load_recording
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording
from envs.replay import Replay

TEST_RECORDINGS = ("biwi_eth", "biwi_hotel", "students001", "students003", "crowds_zara01", "crowds_zara02")


@pytest.mark.parametrize("name", TEST_RECORDINGS)
def test_replay_positions_equal_the_file_at_annotation_times(data_dir: Path, name: str) -> None:
    rec = load_recording(name, data_dir=data_dir)
    times = rec.times_s()
    full = Replay(rec)
    pos, present = full.positions_at(times)
    np.testing.assert_array_equal(present, rec.present)
    np.testing.assert_array_equal(pos[rec.present], rec.positions[rec.present])
    # an episode-sized slice: same values for its pedestrians
    i0, i1 = len(times) // 3, len(times) // 3 + 60
    part = Replay(rec, times[i0], times[i1])
    pos, present = part.positions_at(times[i0 : i1 + 1])
    np.testing.assert_array_equal(present, rec.present[i0 : i1 + 1][:, part.columns])
    mask = rec.present[i0 : i1 + 1][:, part.columns]
    np.testing.assert_array_equal(pos[mask], rec.positions[i0 : i1 + 1][:, part.columns][mask])


def test_replay_interpolates_linearly_in_real_time() -> None:
    # pedestrian 0: 3 annotations; pedestrian 1: appears at the second one; step 2/3 s (ETH-like)
    crowd = scripted_recording([[[0, 0], [1, 0], [3, 0]], [[5, 5], [5, 6]]], start_steps=[0, 1], step_s=2 / 3)
    r = Replay(crowd)
    pos, present = r.positions_at(np.array([1 / 3, 2 / 3, 1.0, 4 / 3, 1.5]))
    np.testing.assert_allclose(pos[:, 0], [[0.5, 0], [1, 0], [2, 0], [3, 0], [3, 0]], atol=1e-12)
    assert present[:, 0].tolist() == [True, True, True, True, False]
    assert present[:, 1].tolist() == [False, True, True, True, False]
    np.testing.assert_allclose(pos[2, 1], [5, 5.5], atol=1e-12)
    state = r.state_at(1.0)
    np.testing.assert_allclose(state.velocities[0], [[3.0, 0.0], [0.0, 1.5]], atol=1e-12)
    # at an annotation time: the following interval's slope, or the preceding one's at the end
    np.testing.assert_allclose(r.state_at(4 / 3).velocities[0, 0], [3.0, 0.0], atol=1e-12)


def test_observed_velocities_do_not_reveal_the_next_annotation(data_dir: Path) -> None:
    # 1 m/s along x for two annotations, then along y (annotations every 0.4 s); the robot stands still
    path = [[2.0, 0.0], [2.4, 0.0], [2.8, 0.0], [2.8, 0.4], [2.8, 0.8]]
    env = CrowdNavEnv(predictor="none", crowd=scripted_recording([path], num_steps=40), flatten_observation=False)
    obs, _ = env.reset(seed=0, options={"t0_s": 0.0, "start": (0.0, -3.0), "goal": (0.0, -11.0)})
    seen = [obs["pedestrians"][0, 2:4].copy()]
    for _ in range(4):
        obs, *_ = env.step(np.zeros(2, dtype=np.float32))
        seen.append(obs["pedestrians"][0, 2:4].copy())
    # at each annotation: the interval that ends there (nothing yet at the first), not the one that starts there
    np.testing.assert_allclose(seen, [[0, 0], [1, 0], [1, 0], [0, 1], [0, 1]], atol=1e-6)
    # between annotations (ETH-like 2/3 s step): the latest annotation's position and arrival slope
    crowd = scripted_recording([[[0, 0], [1, 0], [3, 0]]], step_s=2 / 3)
    r = Replay(crowd)
    for t in (2 / 3, 1.0, 4 / 3 - 1e-3):
        seen = r.perceived_at(t)
        assert seen.index == 1 and seen.time_s == pytest.approx(2 / 3) and seen.present[0]
        assert seen.age_s == pytest.approx(t - 2 / 3, abs=1e-9)
        np.testing.assert_allclose(seen.velocities[0], [1.5, 0.0], atol=1e-12)
        np.testing.assert_allclose(seen.positions[0], [1.0, 0.0], atol=1e-12)
    assert r.perceived_at(4 / 3).velocities[0].tolist() == [3.0, 0.0]
    assert not r.perceived_at(4 / 3 + 0.7).present[0]  # the track is dropped after one annotation step
    # on ZARA1 at 0.4 s: the backward difference of the file, and p + v * 0.4 is not the next annotation
    rec = load_recording("crowds_zara01", data_dir=data_dir)
    times = rec.times_s()
    env = CrowdNavEnv(predictor="none", data_dir=str(data_dir), split="zara1", part="test", flatten_observation=False)
    obs, _ = env.reset(seed=1)
    checked = 0
    for _ in range(5):
        i = int(np.argmin(np.abs(times - env.time_s)))
        assert abs(times[i] - env.time_s) < 1e-6 and times[i] - times[i - 1] == pytest.approx(0.4)
        cols = env.replay.columns[env.observed_rows]
        both = rec.present[i, cols] & rec.present[i - 1, cols]
        backward = np.where(both[:, None], (rec.positions[i, cols] - rec.positions[i - 1, cols]) / 0.4, 0.0)
        ped_velocity = obs["pedestrians"][: len(cols), 2:4] + obs["robot"][2:4]
        np.testing.assert_allclose(ped_velocity, backward, atol=1e-5)
        checked += int(both.sum())
        obs, *_ = env.step(np.zeros(2, dtype=np.float32))
    assert checked > 10


def test_start_clearance_holds_between_annotations() -> None:
    # ETH-like step: a pedestrian 1.64 m from the start at two annotations passes 1.43 m from it in between
    crowd = scripted_recording([[[-1.0, 1.3], [1.0, 1.3]]], start_steps=[1], num_steps=30, step_s=2 / 3)
    env = CrowdNavEnv(predictor="none", crowd=crowd)
    times = crowd.times_s()
    assert env.sampler.clear_m == pytest.approx(1.6)
    pos, present = Replay(crowd).positions_at(np.array([1.2]))
    assert present[0, 0] and np.linalg.norm(pos[0, 0]) < 1.6
    assert not env.sampler._clear(crowd, times, 1.2, np.zeros(2))
    assert env.sampler._clear(crowd, times, 1.2, np.array([0.0, -0.5]))
    assert env.sampler._clear(crowd, times, 2.0, np.zeros(2))  # gone


def test_env_replays_the_file_at_annotation_times(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="none", data_dir=str(data_dir), split="zara1", part="test")
    rec = load_recording("crowds_zara01", data_dir=data_dir)
    times = rec.times_s()
    env.reset(seed=4)
    checked = 0
    for _ in range(30):
        i = int(np.argmin(np.abs(times - env.time_s)))
        # dt_s = 0.4 s: env times are annotation times (except inside gaps of the annotation)
        if abs(times[i] - env.time_s) < 1e-6:
            pos, present = env.replay.positions_at(np.array([env.time_s]))
            cols = env.replay.columns
            np.testing.assert_array_equal(present[0], rec.present[i, cols])
            np.testing.assert_array_equal(pos[0][present[0]], rec.positions[i, cols][present[0]])
            checked += int(present.sum())
        *_, terminated, truncated, _ = env.step(np.zeros(2, dtype=np.float32))
        if terminated or truncated:
            break
    assert checked > 0


@pytest.mark.parametrize(("split", "part"), [("zara1", "test"), ("hotel", "test"), ("eth", "train"), ("eth", "test")])
def test_episodes_cross_the_crowd_from_a_clear_start(data_dir: Path, split: str, part: str) -> None:
    env = CrowdNavEnv(predictor="none", data_dir=str(data_dir), split=split, part=part)
    cfg = env.config
    lo_d, hi_d = cfg.start_goal_distance_m
    names = set()
    for seed in range(40):
        env.reset(seed=seed)
        ep = env.episode
        assert ep is not None
        rec = ep.recording
        names.add(rec.name)
        start, goal = ep.start, ep.goal
        dist = float(np.linalg.norm(goal - start))
        assert lo_d <= dist <= hi_d
        assert ep.time_limit_s == pytest.approx(ep.max_steps * cfg.dt_s)
        assert ep.time_limit_s >= cfg.time_limit_factor * dist / cfg.robot_pref_speed_mps - 1e-9
        times = rec.times_s()
        assert ep.t0_s >= 7 * rec.step_s - 1e-9 and ep.t0_s + ep.time_limit_s <= times[-1] + 1e-9
        # nobody within start_clearance_m (gap) of the start at t0
        pos, present = env.replay.positions_at(np.array([ep.t0_s]))
        gaps = np.linalg.norm(pos[0][present[0]] - start, axis=1) - cfg.robot_radius_m - cfg.pedestrian_radius_m
        assert np.all(gaps >= cfg.start_clearance_m)
        # the straight path passes through a position some pedestrian occupies during the episode
        i0, i1 = np.searchsorted(times, [ep.t0_s - 1e-6, ep.t0_s + ep.time_limit_s + 1e-6])
        occupied = rec.positions[i0:i1][rec.present[i0:i1]]
        u = (goal - start) / dist
        along = np.clip((occupied - start) @ u, 0.0, dist)
        off = np.linalg.norm(occupied - (start + along[:, None] * u), axis=1)
        assert off.min() < 1e-6
    if part == "train":
        assert len(names) >= 3  # several of the other scenes' recordings
