"""Forecast sources for the observation: none, constant velocity, the pretrained structural RNNs,
the replay's true future (oracle) and the true future plus noise (noisy oracle).

Learned forecasts are always out-of-sample: the recording being replayed is forecast by the
pretrained predictor of the split whose held-out scene it is. A predictor sees the pedestrians'
histories up to the current time, sampled from the replay every annotation step of the recording
(``step_s``: 0.4 s, or 0.667 s for ``biwi_eth``); its forecast, on that annotation grid, is resampled
onto the environment's grid ``t + h * dt_s`` (h = 1..H) by linear interpolation in time (beyond the
predictor's last step the last forecast position is held).

Replayed pedestrians ignore the robot, so forecasts depend only on (recording, time): they are
memoised per (recording, time) and a forecast taken from the cache is identical to one computed
online (``tests/envs/test_forecasts.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final, Protocol

import numpy as np

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLIT_TEST_RECORDINGS
from envs.config import LEARNED_SOURCES
from envs.crowds import Replay


class PredictorUnavailableError(FileNotFoundError):
    """A pretrained predictor (its weights) could not be loaded; the message says what and how to get it."""


class ForecastModel(Protocol):
    """What the environment needs of a predictor (:class:`crowdnav_mesrnn.models.Predictor`)."""

    name: str
    obs_len: int
    pred_len: int

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray: ...


def split_of_recording(name: str) -> str | None:
    """The split whose held-out (test) recordings include ``name``; None for other crowds."""
    for split, names in SPLIT_TEST_RECORDINGS.items():
        if name in names:
            return split
    return None


def time_key(t_s: float) -> int:
    """Cache key of a time: tenths of milliseconds (env times are multiples of dt_s, not exact floats)."""
    return round(t_s * 1e4)


@dataclass(frozen=True)
class TrueFuture:
    """The replay's future of some pedestrians on the environment's grid.

    Attributes:
        positions: ``(n, H, 2)`` metres at ``t + h * dt_s``; where the pedestrian has left the replay,
            its last position in the replay is held (so it can serve as an oracle forecast).
        valid: ``(n, H)`` bool: the pedestrian is in the replay at that time.
    """

    positions: np.ndarray
    valid: np.ndarray


def fill_forward(positions: np.ndarray, valid: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Hold the last valid position where ``valid`` is False.

    Args:
        positions: ``(n, H, 2)``; valid: ``(n, H)``; current: ``(n, 2)`` position at h = 0.
    """
    if valid.all():
        return positions.copy()
    h = positions.shape[1]
    idx = np.where(valid, np.arange(1, h + 1)[None, :], 0)
    idx = np.maximum.accumulate(idx, axis=1)
    full = np.concatenate([current[:, None, :], positions], axis=1)
    return np.take_along_axis(full, idx[..., None], axis=1)


def resample_weights(
    step_s: float, dt_s: float, horizon: int, pred_len: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation from the annotation grid ``j * step_s`` (j = 0..pred_len) onto ``h * dt_s`` (h = 1..H).

    Returns:
        ``(j0, j1, w)`` each ``(H,)``: value = (1 - w) * f[j0] + w * f[j1] (held at j = pred_len beyond).
    """
    u = np.arange(1, horizon + 1) * dt_s / step_s
    u = np.minimum(u, pred_len)
    j0 = np.floor(u + 1e-9).astype(np.int64)
    j0 = np.minimum(j0, pred_len)
    w = u - j0
    w = np.where(np.abs(w) < 1e-9, 0.0, w)
    j1 = np.minimum(j0 + 1, pred_len)
    return j0, j1, w


class ForecastSource:
    """Base class: forecasts of some pedestrians of a replay at time ``t``.

    Attributes:
        name: the source's name (``"none"``, ``"cv"``, ``"mesrnn"``, ...).
        needs_truth: the source uses the replay's true future.
    """

    name: str = "base"
    needs_truth: bool = False
    active: bool = True

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        """``(len(rows), H, 2)`` world positions at ``t + h * dt_s`` of the pedestrians in ``rows`` (present at t)."""
        raise NotImplementedError


class NoForecast(ForecastSource):
    """No forecasts in the observation."""

    name = "none"
    active = False

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        return None


class OracleForecast(ForecastSource):
    """The replay's true future (held at the last position once a pedestrian has left)."""

    name = "oracle"
    needs_truth = True

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        assert truth is not None
        return truth.positions.copy()


class NoisyOracleForecast(ForecastSource):
    """The true future plus a drift error that grows linearly over the horizon.

    For each pedestrian and forecast time, ``z ~ N(0, sigma^2 I)`` (2-D) and the error at step h is
    ``(h / H) z``; ``sigma`` is set so the expected ADE is ``target_ade_m``:
    ``E|e_h| = (h / H) sigma sqrt(pi / 2)``, so ``ADE = sigma sqrt(pi / 2) (H + 1) / (2 H)``.
    Noise comes from the environment's generator (seeded by ``reset``); never cached.
    """

    name = "noisy_oracle"
    needs_truth = True

    def __init__(self, target_ade_m: float, horizon: int) -> None:
        self.target_ade_m = float(target_ade_m)
        self.horizon = horizon
        self.sigma = self.target_ade_m * 2 * horizon / ((horizon + 1) * math.sqrt(math.pi / 2))
        self.ramp = (np.arange(1, horizon + 1) / horizon)[None, :, None]

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        assert truth is not None
        z = rng.normal(0.0, self.sigma, size=(len(rows), 1, 2))
        return truth.positions + self.ramp * z


class PredictorForecast(ForecastSource):
    """Forecasts of a trajectory predictor (``forecast(history (8, N, 2), mask (8, N)) -> (N, 12, 2)``).

    Args:
        name: source name.
        predictors: recording name -> predictor; ``default`` is used for any other recording.
        dt_s: environment step, seconds.
        horizon: H, environment steps.
        cache: memoise per (recording, time).
    """

    def __init__(
        self,
        name: str,
        predictors: dict[str, ForecastModel],
        default: ForecastModel | None,
        dt_s: float,
        horizon: int,
        cache: bool = True,
    ) -> None:
        self.name = name
        self.predictors = predictors
        self.default = default
        self.dt_s = dt_s
        self.horizon = horizon
        self.use_cache = cache
        self._cache: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}
        self._weights: dict[tuple[float, int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.calls = 0

    def predictor_for(self, recording: str) -> ForecastModel:
        model = self.predictors.get(recording, self.default)
        if model is None:
            raise ValueError(f"no predictor for recording {recording!r}")
        return model

    def clear_cache(self) -> None:
        self._cache.clear()

    @property
    def cache_size(self) -> int:
        return len(self._cache)

    def all_forecasts(self, replay: Replay, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Forecasts of every pedestrian present at ``t_s``.

        Returns:
            ``(columns (M,), positions (M, H, 2))``: recording columns (ascending) and world
            positions at ``t + h * dt_s``, metres.
        """
        key = (replay.name, time_key(t_s))
        if self.use_cache:
            hit = self._cache.get(key)
            if hit is not None:
                return hit
        out = self._compute(replay, t_s)
        if self.use_cache:
            self._cache[key] = out
        return out

    def _compute(self, replay: Replay, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        model = self.predictor_for(replay.name)
        obs_len = int(getattr(model, "obs_len", OBS_LEN))
        pred_len = int(getattr(model, "pred_len", PRED_LEN))
        step = replay.step_s
        hist_t = t_s - step * np.arange(obs_len - 1, -1, -1)
        state = replay.state_at(hist_t)
        seen = np.flatnonzero(state.present.any(axis=0))
        now = state.present[-1, seen]
        if not now.any():
            return np.zeros(0, dtype=np.int64), np.zeros((0, self.horizon, 2))
        history = state.positions[:, seen].astype(np.float32)
        mask = state.present[:, seen]
        history[~mask] = 0.0
        self.calls += 1
        pred = np.asarray(model.forecast(history, mask), dtype=np.float64)
        if pred.shape != (len(seen), pred_len, 2):
            raise ValueError(
                f"predictor {getattr(model, 'name', model)!r} returned shape {pred.shape}, expected {(len(seen), pred_len, 2)}"
            )
        wkey = (step, obs_len, pred_len)
        if wkey not in self._weights:
            self._weights[wkey] = resample_weights(step, self.dt_s, self.horizon, pred_len)
        j0, j1, w = self._weights[wkey]
        full = np.concatenate([state.positions[-1, seen][:, None, :], pred], axis=1)
        resampled = full[:, j0] * (1.0 - w)[None, :, None] + full[:, j1] * w[None, :, None]
        return replay.columns[seen[now]], resampled[now]

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        cols, fc = self.all_forecasts(replay, t_s)
        if len(rows) == 0:
            return np.zeros((0, self.horizon, 2))
        want = replay.columns[rows]
        idx = np.searchsorted(cols, want)
        idx = np.minimum(idx, max(len(cols) - 1, 0))
        if len(cols) == 0 or not np.array_equal(cols[idx], want):
            raise RuntimeError(f"forecast requested for pedestrians not present at t={t_s:.3f} s in {replay.name}")
        return fc[idx]

    def precompute(self, replay: Replay, times_s: np.ndarray) -> None:
        """Fill the cache at ``times_s`` (no-op without caching)."""
        if not self.use_cache:
            return
        for t in np.asarray(times_s, dtype=np.float64).tolist():
            self.all_forecasts(replay, t)


# ----------------------------------------------------------------------------- construction

_LOADED: dict[tuple[str, str], Any] = {}

WEIGHTS_HELP: Final[str] = (
    "Pretrained weights are looked up by crowdnav_mesrnn.models.pretrained.load_pretrained (package data in "
    "crowdnav_mesrnn/pretrained/); train them with the predictor commands of `crowdnav-mesrnn --help`. To run "
    "without them choose predictor='cv', 'oracle', 'noisy_oracle' or 'none' (e.g. gymnasium.make('CrowdNav-CV-v0')), "
    "or pass your own predictor object as predictor=..."
)


def load_learned(name: str, split: str, needed_for: str) -> Any:
    """The pretrained ``name`` predictor of ``split`` (cached per process).

    Raises:
        PredictorUnavailableError: naming the model, the split, the recording it was needed for,
            the underlying error and how to get the weights.
    """
    key = (name, split)
    if key not in _LOADED:
        from crowdnav_mesrnn import models

        try:
            _LOADED[key] = models.get_predictor(name, split)
        except Exception as exc:  # any failure to load is reported the same way, with its cause
            raise PredictorUnavailableError(
                f"the pretrained {name!r} predictor for split {split!r} (needed to forecast {needed_for}) "
                f"could not be loaded: {type(exc).__name__}: {str(exc).rstrip('.')}. {WEIGHTS_HELP}"
            ) from exc
    return _LOADED[key]


def make_forecast_source(
    predictor: str | ForecastModel,
    recordings: list[str],
    default_split: str,
    dt_s: float,
    horizon: int,
    cache: bool,
    noisy_oracle_ade_m: float,
) -> ForecastSource:
    """The forecast source for a set of recordings.

    Args:
        predictor: a source name or a predictor object (used for every recording).
        recordings: names of the recordings episodes may replay.
        default_split: split whose predictor forecasts recordings that belong to no split's test
            part (synthetic, scripted crowds).
        dt_s: environment step, seconds.
        horizon: H.
        cache: memoise forecasts per (recording, time).
        noisy_oracle_ade_m: target ADE of ``noisy_oracle``.
    """
    if not isinstance(predictor, str):
        if not callable(getattr(predictor, "forecast", None)):
            raise TypeError(
                f"predictor must be a name or an object with a forecast(history, mask) method, got {predictor!r}"
            )
        return PredictorForecast(str(getattr(predictor, "name", "custom")), {}, predictor, dt_s, horizon, cache)
    if predictor == "none":
        return NoForecast()
    if predictor == "oracle":
        return OracleForecast()
    if predictor == "noisy_oracle":
        return NoisyOracleForecast(noisy_oracle_ade_m, horizon)
    if predictor == "cv":
        from crowdnav_mesrnn.models import get_predictor

        return PredictorForecast("cv", {}, get_predictor("cv"), dt_s, horizon, cache)
    if predictor in LEARNED_SOURCES:
        per_recording: dict[str, ForecastModel] = {}
        default: ForecastModel | None = None
        for rec in recordings:
            split = split_of_recording(rec)
            if split is None:
                default = load_learned(predictor, default_split, rec)
            else:
                per_recording[rec] = load_learned(predictor, split, rec)
        return PredictorForecast(predictor, per_recording, default, dt_s, horizon, cache)
    raise ValueError(f"unknown predictor {predictor!r}")
