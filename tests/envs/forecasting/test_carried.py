"""``forecast_memory="carried"``: hidden states carried per pedestrian from its first appearance.

Runs on short prefixes of real recordings with a small random structural RNN, so it needs neither
pretrained weights nor much time.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data import load_recording
from crowdnav_mesrnn.data.recordings import Recording
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.carried import CarriedPredictorForecast
from envs.forecasting.window import PredictorForecast
from envs.recordings import make_recording, scripted_recording

#: Robot far from the crowd, seeing everybody, never ending the episode on contact.
WATCHER: dict[str, Any] = {"sensor_range_m": 200.0, "num_pedestrians": 40, "terminate_on_collision": False}


def prefix(data_dir: Path, name: str, frames: int) -> Recording:
    """The first ``frames`` annotations of a recording, with only the pedestrians seen in them."""
    rec = load_recording(name, data_dir=data_dir)
    cols = np.flatnonzero(rec.present[:frames].any(axis=0))
    return make_recording(
        f"{name}_first{frames}", rec.positions[:frames, cols], rec.present[:frames, cols], rec.step_s, rec.ped_ids[cols]
    )


def by_hand(predictor: Any, rec: Recording) -> list[np.ndarray]:
    """``OnlineForecaster`` over every frame of ``rec`` in order: the ``(P, 12, 2)`` forecast after each frame."""
    online = predictor.online(rec.present.shape[1])
    out = []
    for i in range(len(rec.frames)):
        online.observe(rec.positions[i], rec.present[i])
        out.append(online.forecast().astype(np.float64))
    return out


def watch(env: CrowdNavEnv, t0_s: float, steps: int) -> list[tuple[float, np.ndarray, np.ndarray | None]]:
    """``(time, recording columns observed, world forecasts)`` at reset and after each of ``steps`` standing steps."""
    env.reset(seed=0, options={"t0_s": t0_s, "start": (-40.0, -40.0), "goal": (-40.0, -48.0), "time_limit_s": 40.0})
    out = []
    for n in range(steps + 1):
        if n:
            env.step(np.zeros(2, dtype=np.float32))
        out.append((env.time_s, env.replay.columns[env.observed_rows], env.last_forecasts))
    return out


def test_carried_forecasts_equal_an_online_forecaster_run_by_hand(
    data_dir: Path, tiny_learned_predictor: Callable
) -> None:
    predictor = tiny_learned_predictor()
    rec = prefix(data_dir, "students003", 60)
    env = CrowdNavEnv(predictor=predictor, crowd=rec, forecast_memory="carried", **WATCHER)
    assert isinstance(env.forecaster, CarriedPredictorForecast) and env.forecaster.memory == "carried"
    hand = by_hand(predictor, rec)
    times = rec.times_s()
    compared = 0
    for t, cols, fc in watch(env, 12.0, 20):
        i = int(np.argmin(np.abs(times - t)))
        assert abs(times[i] - t) < 1e-9  # dt_s = step_s: every env time is an annotation time
        assert fc is not None and len(cols) > 10
        np.testing.assert_array_equal(fc, hand[i][cols])
        compared += len(cols)
    assert compared > 300


def test_carried_forecasts_are_shifted_between_eth_annotations(
    data_dir: Path, tiny_learned_predictor: Callable
) -> None:
    predictor = tiny_learned_predictor(seed=1)
    rec = prefix(data_dir, "biwi_eth", 60)
    step = rec.step_s
    assert step == pytest.approx(2 / 3)
    env = CrowdNavEnv(predictor=predictor, crowd=rec, forecast_memory="carried", **WATCHER)
    hand = by_hand(predictor, rec)
    times = rec.times_s()
    shifted = 0
    for t, cols, fc in watch(env, 6.0, 40):
        if not len(cols):
            continue
        assert fc is not None
        i = int(np.searchsorted(times, t + 1e-6)) - 1  # latest annotation at or before t
        tau = times[i]
        shifted += int(t - tau > 1e-6)
        # np.interp over (tau + j * step, [file position at tau, forecast]) at t + h * dt_s, axis by axis
        grid = tau + step * np.arange(13)
        want = t + 0.4 * np.arange(1, 13)
        for k, col in enumerate(cols):
            values = np.concatenate([rec.positions[i, col][None], hand[i][col]], axis=0)
            expected = np.stack([np.interp(want, grid, values[:, a]) for a in range(2)], axis=-1)
            np.testing.assert_allclose(fc[k], expected, rtol=0, atol=1e-9)
        # forecast exactly the pedestrians perceived at t: those annotated at the latest annotation
        assert set(cols.tolist()) == set(np.flatnonzero(rec.present[i]).tolist())
    assert shifted > 20


def test_carried_memory_changes_the_forecasts(data_dir: Path, tiny_learned_predictor: Callable) -> None:
    predictor = tiny_learned_predictor()
    rec = prefix(data_dir, "students003", 60)
    runs = {
        memory: watch(CrowdNavEnv(predictor=predictor, crowd=rec, forecast_memory=memory, **WATCHER), 12.0, 10)
        for memory in ("window", "carried")
    }
    largest = 0.0
    for (t_w, cols_w, fc_w), (t_c, cols_c, fc_c) in zip(runs["window"], runs["carried"], strict=True):
        assert t_w == t_c
        np.testing.assert_array_equal(cols_w, cols_c)
        assert fc_w is not None and fc_c is not None
        largest = max(largest, float(np.abs(fc_w - fc_c).max()))
    assert largest > 0.05


@pytest.mark.parametrize(
    ("name", "frames", "starts"), [("students003", 70, (14.0, 18.0, 15.2)), ("biwi_eth", 50, (8.0, 12.0, 9.2))]
)
def test_carried_cached_and_online_forecasts_are_identical(
    data_dir: Path,
    tiny_learned_predictor: Callable,
    lockstep: Callable,
    name: str,
    frames: int,
    starts: tuple[float, ...],
) -> None:
    predictor = tiny_learned_predictor()
    rec = prefix(data_dir, name, frames)

    def make(cache: bool) -> CrowdNavEnv:
        return CrowdNavEnv(predictor=predictor, crowd=rec, forecast_memory="carried", cache_forecasts=cache)

    cached, online = make(True), make(False)
    # overlapping episodes, the last one going back in time (the online forecaster restarts from the first frame)
    options = [{"t0_s": t0, "start": (1.0, 1.0), "goal": (7.0, 3.0), "time_limit_s": 6.0} for t0 in starts]
    compared = lockstep(cached, online, options)
    assert compared > 20
    assert isinstance(cached.forecaster, CarriedPredictorForecast)
    assert cached.forecaster.cache_size > 0 and online.forecaster.cache_size == 0  # type: ignore[attr-defined]
    # one pass over the recording for the cache; the online forecaster only forecasts the frames it was asked for
    assert cached.forecaster.calls == len(rec.frames)
    assert 0 < online.forecaster.calls < len(rec.frames)  # type: ignore[attr-defined]


def test_forecast_memory_options(
    monkeypatch: pytest.MonkeyPatch, tiny_learned_predictor: Callable, fake_predictor: Callable
) -> None:
    with pytest.raises(ConfigError, match=r"unknown forecast_memory 'hidden'; valid: window, carried"):
        CrowdNavEnv(predictor="none", crowd="empty", forecast_memory="hidden")
    # a predictor object without online(num_slots) cannot carry hidden states
    with pytest.raises(ConfigError, match=r"'carried' needs a predictor with an online\(num_slots\) method"):
        CrowdNavEnv(predictor=fake_predictor(), crowd="empty", forecast_memory="carried")
    # sources without memory ignore it
    for name in ("none", "cv", "oracle", "noisy_oracle"):
        env = CrowdNavEnv(predictor=name, crowd="empty", forecast_memory="carried")
        assert env.forecaster.memory in (None, "window")
    assert isinstance(
        CrowdNavEnv(predictor="cv", crowd="empty", forecast_memory="carried").forecaster, PredictorForecast
    )
    # named learned sources: the out-of-sample predictor of each recording, carried
    from crowdnav_mesrnn import predictors
    from envs.forecasting import factory

    monkeypatch.setattr(predictors, "load", lambda name, split=None: tiny_learned_predictor(name))
    monkeypatch.setattr(factory, "_LOADED", {})
    # scripted recordings under the scenes' names stand in for the files (no data folder needed: any path will do)
    monkeypatch.setattr("envs.config.find_data_dir", lambda data_dir=None: Path("<scripted>"))
    monkeypatch.setattr(
        "envs.crowd_nav.load_recording", lambda name, part, data_dir: scripted_recording([], num_steps=50, name=name)
    )
    env = CrowdNavEnv(predictor="srnn", crowd="replay", split="univ", part="test", forecast_memory="carried")
    assert isinstance(env.forecaster, CarriedPredictorForecast)
    assert sorted(env.forecaster.predictors) == ["students001", "students003"]
    assert env.forecaster.predictor_for("students003").name == "srnn"
