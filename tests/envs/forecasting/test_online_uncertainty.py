"""``forecast_uncertainty_method``: ``split`` keeps the split conformal radii; ``online`` tracks each step's threshold
inside the episode with the observed rule and step-size experts, from the split thresholds, strictly causally."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.uncertainty.conformal import Calibration, ErrorModel
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.resampling import resample_matrix
from envs.forecasting.uncertainty import CalibratedUncertainty, OnlineUncertainty
from envs.forecasting.window import PredictorForecast
from envs.replay import Replay

START = np.linspace(2.0, 2.6, 12)  # the split thresholds of the synthetic calibration (Mahalanobis radii)


class ShiftedVelocity:
    """Constant velocity plus a fixed offset of every forecast step (metres): 0 forecasts straight walkers exactly."""

    obs_len, pred_len, name = 8, 12, "shifted"

    def __init__(self, offset_m: float) -> None:
        self.offset_m = offset_m

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        vel = np.where((mask[-1] & mask[-2])[:, None], history[-1] - history[-2], 0.0)
        k = np.arange(1, 13, dtype=np.float32)[None, :, None]
        return (history[-1][:, None] + k * vel[:, None] + self.offset_m).astype(np.float32)


def walkers(frames: int = 60, shift_after: int | None = None) -> Recording:
    """Six pedestrians walking straight at constant speeds through ``frames`` annotations (0.4 s); with
    ``shift_after``, everyone jumps 2 m sideways after that frame (a future the tracker must not see early)."""
    rng = np.random.default_rng(5)
    start = rng.uniform(-4, 4, (1, 6, 2))
    velocity = rng.uniform(-0.5, 0.5, (1, 6, 2))
    positions = start + np.arange(frames)[:, None, None] * velocity
    if shift_after is not None:
        positions[shift_after + 1 :, :, 0] += 2.0
    present = np.ones((frames, 6), dtype=bool)
    return Recording("crowds_zara01", Path("synthetic"), 0.4, np.arange(frames) * 10, np.arange(6), positions, present)


def sources(offset_m: float) -> tuple[CalibratedUncertainty, OnlineUncertainty]:
    """The split radii of a hand-made ``scaled`` calibration (isotropic error model of 0.1 m) and the online radii of
    the same calibration over :class:`ShiftedVelocity` forecasts."""
    cal = Calibration(
        "cv", "point", "zara1", "scaled", {"0.9": tuple(START)}, ErrorModel((0.1,) * 12, (0.0,) * 12), 1, 1
    )
    split = CalibratedUncertainty("cv", "zara1", 0.9, 0.4, 12, None)
    split._calibrations["zara1"] = cal
    forecaster = PredictorForecast("shifted", {}, ShiftedVelocity(offset_m), 0.4, 12, cache=False)
    return split, OnlineUncertainty(split, forecaster)


def online_radii(rec: Recording, offset_m: float, first: int, last: int) -> tuple[np.ndarray, np.ndarray]:
    """``(online (F, 6, 12), split (F, 6, 12))`` radii at annotations ``first..last`` of one episode of ``rec``."""
    split, online = sources(offset_m)
    replay = Replay(rec)
    episode = online.for_episode(replay, first)
    rows = np.arange(6)
    out, ref = [], []
    for k in range(first, last + 1):
        out.append(episode.radius(replay, float(replay.times[k]), rows, 0.0, k))
        ref.append(split.radius(replay, float(replay.times[k]), rows, 0.0, k))
    return np.stack(out), np.stack(ref)


def test_the_first_annotation_gets_the_split_radii_bit_for_bit() -> None:
    online, split = online_radii(walkers(), 1.0, 7, 9)
    np.testing.assert_array_equal(online[0], split[0])
    assert np.all(np.isfinite(online)) and np.all(online >= 0)


@pytest.mark.parametrize(("offset_m", "direction"), [(1.0, 1.0), (0.0, -1.0)], ids=["misses", "over-covers"])
def test_thresholds_move_towards_the_level(offset_m: float, direction: float) -> None:
    """Forecasts 1 m off with a 0.1 m error model miss every region: the radii grow; exact forecasts never miss:
    they shrink. Step h is first revealed h annotations after the first forecast."""
    online, split = online_radii(walkers(), offset_m, 7, 45)
    np.testing.assert_array_equal(online[1][:, 1:], split[1][:, 1:])  # one annotation on: only step 1 was revealed
    assert direction * (online[1][:, 0] - split[1][:, 0]).min() > 0
    assert np.all(direction * (online[-1] - split[-1]) > 0)
    assert np.all(np.isfinite(online)) and np.all(online >= 0)


def test_radii_at_t_do_not_depend_on_positions_after_t() -> None:
    base, _ = online_radii(walkers(), 0.5, 7, 40)
    changed, _ = online_radii(walkers(shift_after=20), 0.5, 7, 40)
    np.testing.assert_array_equal(changed[: 20 - 7 + 1], base[: 20 - 7 + 1])  # annotations 7..20
    assert not np.array_equal(changed[-1], base[-1])  # the shifted positions are learned from once annotated


def test_a_new_episode_restarts_the_tracker() -> None:
    split, online = sources(1.0)
    replay = Replay(walkers())
    rows = np.arange(6)
    first = online.for_episode(replay, 7)
    for k in range(7, 30):
        first.radius(replay, float(replay.times[k]), rows, 0.0, k)
    again = online.for_episode(replay, 7).radius(replay, float(replay.times[7]), rows, 0.0, 7)
    np.testing.assert_array_equal(again, split.radius(replay, float(replay.times[7]), rows, 0.0, 7))
    with pytest.raises(RuntimeError, match="for_episode"):
        online.radius(replay, float(replay.times[7]), rows, 0.0, 7)


def test_a_bad_method_is_refused_naming_key_value_and_the_allowed_ones() -> None:
    with pytest.raises(ConfigError, match=r"forecast_uncertainty_method 'causal'; valid: split, online"):
        CrowdNavEnv(crowd="empty", predictor="none", forecast_uncertainty_method="causal")


def test_online_needs_pedestrians_who_do_not_react(data_dir: Path) -> None:
    with pytest.raises(ConfigError, match=r"forecast_uncertainty_method.*reaction 'none'"):
        CrowdNavEnv(
            predictor="cv",
            split="zara1",
            part="test",
            forecast_uncertainty=True,
            forecast_uncertainty_method="online",
            reaction="pause",
        )


def todays_radii(env: CrowdNavEnv) -> np.ndarray:
    """The split radii of the perceived rows, computed as the environment computed them before the method existed:
    the split threshold times the error model's scale at the last displacement, resampled onto the env's grid."""
    replay = env._tracked()
    seen = replay.perceived_at(env.time_s)
    rows = env._last["rows"]
    speed = np.zeros(len(rows))
    if seen.index >= 1:
        both = replay.present[seen.index, rows] & replay.present[seen.index - 1, rows]
        disp = replay.positions[seen.index, rows] - replay.positions[seen.index - 1, rows]
        speed = np.where(both, np.hypot(disp[:, 0], disp[:, 1]), 0.0)
    assert env.uncertainty is not None
    cal = env.uncertainty.calibration("eth")  # type: ignore[attr-defined]
    per_step = cal.threshold(0.9)[None, :] * cal.error_model.sigma(speed)
    weights = resample_matrix(replay.step_s, env.config.dt_s, env.config.horizon_steps, 12, seen.age_s)
    return per_step @ weights[:, 1:].T


def run(method: str | None, steps: int, seed: int = 3, **kw: Any) -> tuple[CrowdNavEnv, list[np.ndarray]]:
    """An episode of cv on held-out ETH (0.667 s annotations, resampled onto 0.4 s steps) walking to the goal."""
    extra = {} if method is None else {"forecast_uncertainty_method": method}
    env = CrowdNavEnv(predictor="cv", split="eth", part="test", forecast_uncertainty=True, **extra, **kw)
    obs, _ = env.reset(seed=seed)
    out = [obs["forecast_uncertainty"].copy()]
    for _ in range(steps):
        goal = obs["robot"][:2]
        obs, _, terminated, truncated, _ = env.step(np.clip(goal / max(np.linalg.norm(goal), 1e-9), -1, 1))
        out.append(obs["forecast_uncertainty"].copy())
        if terminated or truncated:
            break
    return env, out


def test_split_gives_todays_radii_bit_for_bit(data_dir: Path) -> None:
    env = CrowdNavEnv(
        predictor="cv", split="eth", part="test", forecast_uncertainty=True, forecast_uncertainty_method="split"
    )
    obs, _ = env.reset(seed=3)
    default, _ = run(None, 0)
    checked = 0
    for _ in range(12):
        m = int(obs["mask"].sum())
        expected = np.clip(todays_radii(env), 0.0, env._builder.fc_bound).astype(np.float32)
        np.testing.assert_array_equal(obs["forecast_uncertainty"].reshape(10, 12)[:m], expected)
        checked += m
        obs, *_ = env.step(np.zeros(2, np.float32))
    assert checked > 0
    assert dataclasses.replace(default.config, forecast_uncertainty_method="split") == env.config


def test_online_starts_at_split_restarts_on_reset_and_stays_finite(data_dir: Path) -> None:
    _, split = run("split", 40)
    env, online = run("online", 40)
    assert np.any(split[0]) and len(online) > 13
    np.testing.assert_array_equal(online[0], split[0])
    assert not all(np.array_equal(a, b) for a, b in zip(online, split, strict=True))  # the thresholds moved
    assert all(np.all(np.isfinite(r)) and np.all(r >= 0) for r in online)
    obs, _ = env.reset(seed=3)  # a new episode starts from the split thresholds again
    np.testing.assert_array_equal(obs["forecast_uncertainty"], split[0])


def test_cv_gaussian_has_calibrated_radii(data_dir: Path) -> None:
    for method in ("split", "online"):
        env = CrowdNavEnv(
            predictor="cv_gaussian",
            split="zara1",
            part="test",
            forecast_uncertainty=True,
            forecast_uncertainty_method=method,
        )
        obs, _ = env.reset(seed=1)
        for _ in range(15):
            obs, *_ = env.step(np.zeros(2, np.float32))
        radii = obs["forecast_uncertainty"].reshape(10, 12)[obs["mask"].astype(bool)]
        assert len(radii) and np.all(np.isfinite(radii)) and np.all(np.diff(radii, axis=1) >= 0)
