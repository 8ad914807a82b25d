"""Forecast sources: oracle = replay future, cached = online, resampling onto the env grid, out-of-sample
predictors."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.data import load_recording
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.resampling import resample_weights
from envs.forecasting.sources import NoisyOracleForecast, TrueFuture
from envs.forecasting.window import PredictorForecast
from envs.recordings import scripted_recording
from envs.replay import Replay


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
    truth = TrueFuture(np.zeros((20000, 12, 2)), np.ones((20000, 12), dtype=bool))
    fc = source.forecast(None, 0.0, np.arange(20000), truth, np.random.default_rng(0))  # type: ignore[arg-type]
    ade = np.linalg.norm(fc, axis=-1).mean()
    assert ade == pytest.approx(0.5, rel=0.02)


def test_learned_forecasts_are_out_of_sample(monkeypatch: pytest.MonkeyPatch, fake_predictor: Callable) -> None:
    from crowdnav_mesrnn import predictors
    from envs.forecasting import factory

    monkeypatch.setattr(predictors, "load", lambda name, split=None: fake_predictor(f"{name}-{split}"))
    monkeypatch.setattr(factory, "_LOADED", {})
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
