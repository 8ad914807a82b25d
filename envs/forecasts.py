"""Forecast sources for the observation: none, constant velocity, the pretrained structural RNNs,
the replay's true future (oracle) and the true future plus noise (noisy oracle).

Learned forecasts are always out-of-sample: the recording being replayed is forecast by the
pretrained predictor of the split whose held-out scene it is. A predictor sees the pedestrians'
histories up to the current time, sampled from the replay every annotation step of the recording
(``step_s``: 0.4 s, or 0.667 s for ``biwi_eth``); its forecast, on that annotation grid, is resampled
onto the environment's grid ``t + h * dt_s`` (h = 1..H) by linear interpolation in time (beyond the
predictor's last step the last forecast position is held).

With ``forecast_memory="carried"`` a learned predictor instead carries its hidden states per
pedestrian from the pedestrian's first appearance (:class:`CarriedPredictorForecast`): an online
forecaster fed every annotation frame of the recording in order, whose forecast at the latest
annotation at or before the current time is resampled onto the same grid.

Replayed pedestrians ignore the robot, so forecasts depend only on (recording, time): they are
memoised per (recording, time) and a forecast taken from the cache is identical to one computed
online (``tests/envs/test_replay_and_forecasts.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final, Protocol

import numpy as np

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLIT_TEST_RECORDINGS
from crowdnav_mesrnn.data.recordings import Recording
from envs.config import FORECAST_MEMORIES, LEARNED_SOURCES
from envs.crowds import TIME_TOL_S, Replay


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
    step_s: float, dt_s: float, horizon: int, pred_len: int, offset_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation from the annotation grid ``j * step_s`` (j = 0..pred_len) onto ``offset_s + h * dt_s``
    (h = 1..H); ``offset_s`` >= 0 is how far the wanted grid's origin lies after the annotation grid's.

    Returns:
        ``(j0, j1, w)`` each ``(H,)``: value = (1 - w) * f[j0] + w * f[j1] (held at j = pred_len beyond).
    """
    u = (offset_s + np.arange(1, horizon + 1) * dt_s) / step_s
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
    memory: str | None = None
    """``window`` or ``carried`` for predictor sources, None for sources without memory."""

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
        self.memory = "window"
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


class _CarriedWalk:
    """One online forecaster walking a recording's annotation frames in order (slot = recording column).

    :meth:`at` observes frames up to ``i`` (restarting from the first frame when asked for an earlier
    one) and returns the forecast at frame ``i`` of the pedestrians present there.
    """

    def __init__(self, model: Any, recording: Recording) -> None:
        self.model = model
        self.recording = recording
        self.num_slots = int(recording.present.shape[1])
        self.pred_len = int(getattr(model, "pred_len", PRED_LEN))
        self.forecaster: Any = None
        self.observed = 0  # frames 0 .. observed - 1 have been fed
        self.last: tuple[int, np.ndarray, np.ndarray] | None = None
        self.calls = 0

    def at(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, pred_len, 2) float32 metres)`` at annotation frame ``i``."""
        if self.last is not None and self.last[0] == i:
            return self.last[1], self.last[2]
        rec = self.recording
        if self.forecaster is None or i < self.observed - 1:
            self.forecaster = self.model.online(self.num_slots)
            self.observed = 0
        while self.observed <= i:
            self.forecaster.observe(rec.positions[self.observed], rec.present[self.observed])
            self.observed += 1
        cols = np.flatnonzero(rec.present[i])
        pred = np.asarray(self.forecaster.forecast())
        self.calls += 1
        if pred.shape != (self.num_slots, self.pred_len, 2):
            raise ValueError(
                f"online forecaster of {getattr(self.model, 'name', self.model)!r} returned shape {pred.shape}, "
                f"expected {(self.num_slots, self.pred_len, 2)}"
            )
        out = np.ascontiguousarray(pred[cols], dtype=np.float32)
        self.last = (i, cols, out)
        return cols, out


class CarriedPredictorForecast(PredictorForecast):
    """Forecasts of a recurrent predictor carrying hidden states per pedestrian (``forecast_memory="carried"``).

    The predictor's ``online(num_slots)`` forecaster (:class:`crowdnav_mesrnn.models.learned.OnlineForecaster`)
    gets one slot per pedestrian id of the recording and observes every annotation frame of the whole
    recording in time order from its first frame (the file's positions and presence, frames as in the file:
    the predictor's training windows also step over annotation gaps frame by frame), so each pedestrian's
    hidden states run from its first appearance. Its forecast at frame ``i`` covers ``tau + j * step_s``
    (j = 1..pred_len, ``tau`` = the frame's time). At env time ``t`` the latest frame with ``tau <= t`` is
    used: the file's position at ``tau`` (j = 0) and the forecast are resampled linearly onto
    ``t + h * dt_s``, i.e. with the interpolation shifted by ``t - tau`` (non-zero on ``biwi_eth``, whose
    0.667 s annotations fall between env times); beyond the last forecast step it is held. A pedestrian is
    forecast when the replay has it at ``t`` (present at ``tau``, and at the next frame when ``t > tau``).
    The forecaster only ever sees frames up to ``t``.

    With ``cache=True`` a recording's forecasts at all its frames are computed in one pass on first use
    (replayed pedestrians ignore the robot) and the resampled forecasts memoised per (recording, time).
    With ``cache=False`` (online) a forecaster per recording advances frame by frame as the env's time
    does, restarting from the first frame when an episode goes back in time. Both feed the same frames
    in the same order, so they give identical forecasts. Cost: every step of the forecaster runs all of
    the recording's pedestrians as slots (absent ones masked), so one pass over a long, busy recording
    (``students003``: 541 frames, 434 pedestrians) takes minutes with paper-size weights on one core.

    Args: as :class:`PredictorForecast`; every predictor must have an ``online(num_slots)`` method.
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
        super().__init__(name, predictors, default, dt_s, horizon, cache)
        self.memory = "carried"
        for model in [*predictors.values(), *([default] if default is not None else [])]:
            if not callable(getattr(model, "online", None)):
                raise ConfigError(
                    f"forecast_memory 'carried' needs a predictor with an online(num_slots) method (hidden states "
                    f"carried between steps); {getattr(model, 'name', model)!r} has none. Use forecast_memory 'window'."
                )
        self._tables: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._walks: dict[str, _CarriedWalk] = {}
        self._shifted: dict[tuple[float, int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def clear_cache(self) -> None:
        super().clear_cache()
        self._tables.clear()
        self._walks.clear()

    def _walk(self, recording: Recording) -> _CarriedWalk:
        walk = self._walks.get(recording.name)
        if walk is None or walk.recording is not recording:
            walk = _CarriedWalk(self.predictor_for(recording.name), recording)
            self._walks[recording.name] = walk
        return walk

    def frame_forecasts(self, recording: Recording, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, pred_len, 2) float32)`` at annotation frame ``i`` of ``recording`` for the
        pedestrians present there (recording columns, ascending; metres on the annotation grid after the frame)."""
        if not self.use_cache:
            walk = self._walk(recording)
            before = walk.calls
            out = walk.at(i)
            self.calls += walk.calls - before
            return out
        table = self._tables.get(recording.name)
        if table is None:
            walk = _CarriedWalk(self.predictor_for(recording.name), recording)
            parts = [walk.at(k) for k in range(len(recording.frames))]
            self.calls += walk.calls
            sizes = np.array([len(c) for c, _ in parts], dtype=np.int64)
            offsets = np.concatenate([[0], np.cumsum(sizes)])
            cols = np.concatenate([c for c, _ in parts]) if parts else np.zeros(0, dtype=np.int64)
            fcs = np.concatenate([f for _, f in parts]) if parts else np.zeros((0, walk.pred_len, 2), np.float32)
            table = (offsets, cols, fcs)
            self._tables[recording.name] = table
        offsets, cols, fcs = table
        return cols[offsets[i] : offsets[i + 1]], fcs[offsets[i] : offsets[i + 1]]

    def _compute(self, replay: Replay, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        rec = replay.recording
        empty = (np.zeros(0, dtype=np.int64), np.zeros((0, self.horizon, 2)))
        times = rec.times_s()
        i = int(np.searchsorted(times, t_s + TIME_TOL_S, "right")) - 1
        if i < 0 or rec.present.shape[1] == 0:
            return empty
        offset = float(t_s - times[i])
        on_frame = offset <= TIME_TOL_S
        if not on_frame and i + 1 >= len(times):
            return empty  # after the recording's last annotation nobody is replayed
        cols, fc = self.frame_forecasts(rec, i)
        if not on_frame:
            keep = rec.present[i + 1, cols]
            cols, fc = cols[keep], fc[keep]
        if len(cols) == 0:
            return empty
        offset = 0.0 if on_frame else offset
        pred_len = fc.shape[1]
        wkey = (float(rec.step_s), pred_len, time_key(offset))
        if wkey not in self._shifted:
            self._shifted[wkey] = resample_weights(float(rec.step_s), self.dt_s, self.horizon, pred_len, offset)
        j0, j1, w = self._shifted[wkey]
        full = np.concatenate([rec.positions[i, cols][:, None, :], fc.astype(np.float64)], axis=1)
        return cols, full[:, j0] * (1.0 - w)[None, :, None] + full[:, j1] * w[None, :, None]


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
    memory: str = "window",
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
        memory: ``window`` or ``carried`` (see :attr:`envs.config.CrowdNavConfig.forecast_memory`); ignored by
            ``none``, ``cv``, ``oracle`` and ``noisy_oracle``.

    Raises:
        ConfigError: ``carried`` with a predictor object (or loaded predictor) without ``online(num_slots)``.
    """
    if memory not in FORECAST_MEMORIES:
        raise ConfigError(f"unknown forecast_memory {memory!r}; valid: {', '.join(FORECAST_MEMORIES)}")
    learned_cls = CarriedPredictorForecast if memory == "carried" else PredictorForecast
    if not isinstance(predictor, str):
        if not callable(getattr(predictor, "forecast", None)):
            raise TypeError(
                f"predictor must be a name or an object with a forecast(history, mask) method, got {predictor!r}"
            )
        return learned_cls(str(getattr(predictor, "name", "custom")), {}, predictor, dt_s, horizon, cache)
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
        return learned_cls(predictor, per_recording, default, dt_s, horizon, cache)
    raise ValueError(f"unknown predictor {predictor!r}")
