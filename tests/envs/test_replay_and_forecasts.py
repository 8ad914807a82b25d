"""The replay against the files, and forecasts: oracle = replay future, cached = online, out-of-sample predictors."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.data import load_recording
from envs.crowd_nav import CrowdNavEnv
from envs.forecasts import NoisyOracleForecast, PredictorForecast, resample_weights
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


@pytest.mark.parametrize(("split", "kwargs"), [("zara1", {}), ("eth", {"flatten_observation": False})])
def test_oracle_forecasts_equal_the_replay_future(data_dir: Path, split: str, kwargs: dict[str, Any]) -> None:
    env = CrowdNavEnv(predictor="oracle", data_dir=str(data_dir), split=split, part="test", **kwargs)
    cfg = env.config
    h = cfg.horizon_steps
    env.action_space.seed(0)
    env.reset(seed=0)
    compared = 0
    for _ in range(150):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        rows = env.observed_rows
        fc = env.last_forecasts
        if len(rows):
            assert fc is not None
            future, valid = env.replay.positions_at(env.time_s + cfg.dt_s * np.arange(1, h + 1))
            truth = future[:, rows].transpose(1, 0, 2)
            valid = valid[:, rows].T
            np.testing.assert_array_equal(fc[valid], truth[valid])
            compared += int(valid.sum())
            shaped = obs["forecasts"].reshape(cfg.num_pedestrians, h, 2)
            np.testing.assert_allclose(shaped[: len(rows)], fc - env.robot_position, atol=1e-5)
            assert not shaped[len(rows) :].any()
        if terminated or truncated:
            env.reset()
    assert compared > 100


@pytest.mark.parametrize("which", ["cv", "fake"])
def test_cached_and_online_forecasts_are_identical(
    data_dir: Path, which: str, fake_predictor: Callable, lockstep: Callable
) -> None:
    def make(cache: bool) -> CrowdNavEnv:
        predictor = fake_predictor() if which == "fake" else "cv"
        return CrowdNavEnv(
            predictor=predictor, data_dir=str(data_dir), split="univ", part="test", cache_forecasts=cache
        )

    cached, online = make(True), make(False)
    # overlapping episodes in the same recording: later ones are served from the first one's cache
    options = [{"recording": "students003", "t0_s": t0} for t0 in (100.0, 102.0, 101.2)]
    assert lockstep(cached, online, options) > 0
    assert isinstance(cached.forecaster, PredictorForecast) and isinstance(online.forecaster, PredictorForecast)
    assert cached.forecaster.cache_size > 0 and online.forecaster.cache_size == 0
    calls = cached.forecaster.calls
    assert lockstep(cached, online, options[:1]) > 0
    assert cached.forecaster.calls == calls  # served from the table


def test_forecasts_do_not_depend_on_the_episode_slice(data_dir: Path, fake_predictor: Callable) -> None:
    rec = load_recording("students003", data_dir=data_dir)
    source = PredictorForecast("fake", {}, fake_predictor(), 0.4, 12, cache=False)
    full = Replay(rec)
    for t in (20.0, 55.2, 100.4):
        piece = Replay(rec, t - 4.0, t + 10.0)
        cols_a, fc_a = source.all_forecasts(full, t)
        cols_b, fc_b = source.all_forecasts(piece, t)
        np.testing.assert_array_equal(cols_a, cols_b)
        np.testing.assert_array_equal(fc_a, fc_b)
        assert len(cols_a) > 10


def test_precomputed_cache_serves_episodes(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="cv", data_dir=str(data_dir), split="zara1", part="test")
    n = env.precompute_forecasts()
    assert n == len(load_recording("crowds_zara01", data_dir=data_dir).frames)
    calls = env.forecaster.calls  # type: ignore[attr-defined]
    env.reset(seed=0)
    for _ in range(10):
        env.step(np.zeros(2, dtype=np.float32))
    assert env.forecaster.calls == calls  # type: ignore[attr-defined]


def test_predictor_sees_histories_sampled_at_annotation_steps(data_dir: Path, fake_predictor: Callable) -> None:
    predictor = fake_predictor(record=True)
    env = CrowdNavEnv(predictor=predictor, data_dir=str(data_dir), split="zara2", part="test", cache_forecasts=False)
    rec = load_recording("crowds_zara02", data_dir=data_dir)
    times = rec.times_s()
    env.reset(seed=2)
    for _ in range(50):
        before = len(predictor.calls)
        env.step(np.zeros(2, dtype=np.float32))
        if len(predictor.calls) > before:
            break
    history, mask = predictor.calls[-1]  # the forecast at env.time_s
    i = int(np.argmin(np.abs(times - env.time_s)))
    window = slice(i - 7, i + 1)
    cols = np.flatnonzero(rec.present[window].any(axis=0))
    np.testing.assert_array_equal(mask, rec.present[window][:, cols])
    np.testing.assert_array_equal(history[mask], rec.positions[window][:, cols][mask].astype(np.float32))


def test_forecasts_are_resampled_onto_the_env_grid() -> None:
    # ETH-like annotations every 2/3 s; a pedestrian walking at (0.9, -0.3) m/s
    velocity = np.array([0.9, -0.3])
    path = np.array([1.0, 2.0]) + velocity * (2 / 3) * np.arange(60)[:, None]
    crowd = scripted_recording([path], step_s=2 / 3, name="eth_like")
    env = CrowdNavEnv(predictor="cv", crowd=crowd)
    env.reset(seed=0, options={"t0_s": 8.0, "start": (20.0, 20.0), "goal": (20.0, 28.0)})
    assert env.config.sensor_range_m < 30  # the pedestrian is far: ask the source directly
    t = env.time_s
    rows = np.array([0])
    fc = env.forecaster.forecast(env.replay, t, rows, None, env.np_random)
    now = env.replay.positions_at(np.array([t]))[0][0, 0]
    expected = now + velocity * 0.4 * np.arange(1, 13)[:, None]
    np.testing.assert_allclose(fc[0], expected, atol=1e-5)
    j0, j1, w = resample_weights(2 / 3, 0.4, 12, 12)
    grid = np.arange(13) * 2 / 3
    values = np.sin(grid)
    np.testing.assert_allclose((1 - w) * values[j0] + w * values[j1], np.interp(0.4 * np.arange(1, 13), grid, values))


def test_noisy_oracle_reaches_the_target_ade() -> None:
    source = NoisyOracleForecast(target_ade_m=0.5, horizon=12)
    from envs.forecasts import TrueFuture

    truth = TrueFuture(np.zeros((20000, 12, 2)), np.ones((20000, 12), dtype=bool))
    fc = source.forecast(None, 0.0, np.arange(20000), truth, np.random.default_rng(0))  # type: ignore[arg-type]
    ade = np.linalg.norm(fc, axis=-1).mean()
    assert ade == pytest.approx(0.5, rel=0.02)


def test_learned_forecasts_are_out_of_sample(monkeypatch: pytest.MonkeyPatch, fake_predictor: Callable) -> None:
    from crowdnav_mesrnn import models
    from envs import forecasts

    monkeypatch.setattr(models, "get_predictor", lambda name, split=None: fake_predictor(f"{name}-{split}"))
    monkeypatch.setattr(forecasts, "_LOADED", {})
    # scripted recordings under the scenes' names stand in for the files (no data folder needed: any path will do)
    monkeypatch.setattr("envs.config.find_data_dir", lambda data_dir=None: Path("<scripted>"))
    monkeypatch.setattr(
        "envs.crowd_nav.load_recording", lambda name, part, data_dir: scripted_recording([], num_steps=50, name=name)
    )
    env = CrowdNavEnv(predictor="mesrnn", crowd="replay", split="zara1", part="train")
    assert isinstance(env.forecaster, PredictorForecast)
    used = {rec: p.name for rec, p in env.forecaster.predictors.items()}
    assert used == {
        "biwi_eth": "mesrnn-eth",
        "biwi_hotel": "mesrnn-hotel",
        "students001": "mesrnn-univ",
        "students003": "mesrnn-univ",
        "crowds_zara02": "mesrnn-zara2",
    }
    env = CrowdNavEnv(predictor="vlstm", crowd="replay", split="univ", part="test")
    assert {r: p.name for r, p in env.forecaster.predictors.items()} == {  # type: ignore[attr-defined]
        "students001": "vlstm-univ",
        "students003": "vlstm-univ",
    }
    env = CrowdNavEnv(predictor="srnn", crowd="synthetic", split="hotel")
    assert env.forecaster.default.name == "srnn-hotel"  # type: ignore[attr-defined]


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
