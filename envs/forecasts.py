"""Forecast sources for the observation: none, constant velocity, the pretrained structural RNNs,
the replay's true future (oracle) and the true future plus noise (noisy oracle).

Learned forecasts are always out-of-sample: the recording being replayed is forecast by the
pretrained predictor of the split whose held-out scene it is. Forecasts are causal: at env time ``t``
they come from the latest annotation at or before ``t`` (the one the robot perceives), with the
pedestrians' histories of the last 8 annotation steps up to it (``step_s``: 0.4 s, or 0.667 s for
``biwi_eth``); the forecast, on that annotation grid, is resampled onto the environment's grid
``t + h * dt_s`` (h = 1..H) by linear interpolation in time (beyond the predictor's last step the last
forecast position is held).

With ``forecast_memory="carried"`` a learned predictor instead carries its hidden states per
pedestrian from the pedestrian's first appearance (:class:`CarriedPredictorForecast`): an online
forecaster fed every annotation frame of the recording in order.

Replayed pedestrians ignore the robot, so forecasts depend only on (predictor, recording, annotation
frame): a recording's forecasts at all its frames form a :class:`FrameTable`, and a forecast taken from
it is identical to one computed online (``tests/envs/test_replay_and_forecasts.py``).
"""

from __future__ import annotations

import bisect
import contextlib
import math
import multiprocessing
import os
import sys
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Final, Protocol

import numpy as np

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLIT_TEST_RECORDINGS
from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.models.base import ConstantVelocity
from envs.config import FORECAST_MEMORIES, FORECAST_SOURCES, LEARNED_SOURCES, check_predictor_name, is_plugin_source
from envs.forecast_cache import (
    CHUNK_FRAMES,
    ForecastStore,
    FrameTable,
    TableKey,
    chunk_frames,
    num_chunks,
    predictor_fingerprint,
    recording_fingerprint,
)
from envs.replay import TIME_TOL_S, Replay


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


def resample_matrix(step_s: float, dt_s: float, horizon: int, pred_len: int, offset_s: float = 0.0) -> np.ndarray:
    """:func:`resample_weights` as a ``(H, pred_len + 1)`` matrix: row ``h`` weighs the values at ``j = 0..pred_len``."""
    j0, j1, w = resample_weights(step_s, dt_s, horizon, pred_len, offset_s)
    matrix = np.zeros((horizon, pred_len + 1))
    rows = np.arange(horizon)
    np.add.at(matrix, (rows, j0), 1.0 - w)
    np.add.at(matrix, (rows, j1), w)
    return matrix


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


#: Recordings whose forecasts by a predictor without weights (:func:`definition_key`) this process keeps, shared by
#: every source (the environments of a vectorised env, a grid cell's warm start, training and validation).
SHARED_RECORDINGS: Final[int] = 64
_SHARED_TABLES: OrderedDict[tuple[Any, ...], dict[int, FrameTable]] = OrderedDict()


def definition_key(model: Any) -> tuple[Any, ...] | None:
    """What determines the forecasts of a predictor defined by its code alone, or None for any other.

    Only :class:`~crowdnav_mesrnn.models.ConstantVelocity` itself (not a subclass, which may forecast otherwise)
    qualifies: it has no weights and forecasts each pedestrian from its own history alone, so its forecasts of a
    recording depend on ``(obs_len, pred_len)`` and the recording's content. :class:`PredictorForecast` then computes
    a recording's whole table at once, each chunk in one call (:meth:`PredictorForecast._independent_chunk`), and
    shares it with every other source of the process instead of each environment computing its own. They are
    not written to the disk cache, whose key would then have to hash this code rather than weights; a process
    computes a recording's table once.
    """
    if type(model) is ConstantVelocity:
        return ("ConstantVelocity", int(model.obs_len), int(model.pred_len))
    return None


def _share(key: tuple[Any, ...], tables: dict[int, FrameTable]) -> None:
    """Keep ``tables`` for the process under ``key`` (the least recently used recording beyond
    :data:`SHARED_RECORDINGS` is forgotten). Their arrays are made read-only: every source of the process hands out
    views of them (:meth:`PredictorForecast.frame_forecasts`), so a caller writing into one would change the
    forecasts of every other environment."""
    for table in tables.values():
        for array in (table.offsets, table.columns, table.forecasts):
            array.setflags(write=False)
    _SHARED_TABLES[key] = {**_SHARED_TABLES.get(key, {}), **tables}
    _SHARED_TABLES.move_to_end(key)
    while len(_SHARED_TABLES) > SHARED_RECORDINGS:
        _SHARED_TABLES.popitem(last=False)


def clear_shared_tables() -> None:
    """Forget the forecasts shared by this process's sources (:func:`definition_key`)."""
    _SHARED_TABLES.clear()


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
    """Forecasts of a trajectory predictor (``forecast(history (8, N, 2), mask (8, N)) -> (N, 12, 2)``), causal.

    At env time ``t`` the robot perceives the latest annotation at or before ``t`` (time ``tau``; see
    :meth:`envs.replay.Replay.perceived_at`), and its forecasts come from that same annotation: the predictor
    sees the histories of the last ``obs_len`` annotation steps up to ``tau`` (sampled every ``step_s``), and its
    forecast on the annotation grid ``tau + j * step_s`` is resampled linearly onto ``t + h * dt_s`` (the
    interpolation shifted by ``t - tau``, non-zero between ``biwi_eth`` annotations). Nothing annotated after
    ``tau`` enters.

    Forecasts therefore depend only on (predictor, recording, annotation frame). With ``cache=True`` they are
    kept per chunk of :data:`~envs.forecast_cache.CHUNK_FRAMES` frames (:class:`FrameTable`): a chunk is loaded
    from the shared disk cache (``store``) or computed (one predictor call per frame) and written there. With
    ``cache=False`` each frame is computed alone when an env time needs it (the reference path). Both give
    identical forecasts, bit for bit.

    Args:
        name: source name.
        predictors: recording name -> predictor; ``default`` is used for any other recording.
        dt_s: environment step, seconds.
        horizon: H, environment steps.
        cache: keep the forecasts (per chunk of frames, and resampled per time).
        store: the shared disk cache (None: memory only). Predictors without weights to hash
            (:func:`~envs.forecast_cache.predictor_fingerprint`) are kept in memory only; constant velocity's
            tables are shared by every source of the process (:func:`definition_key`).

    Computing runs torch on :attr:`threads` threads, one by default (:func:`torch_threads`; the caller's setting
    is restored after): a frame's batched operations are small, and more threads contend for the cores (on the
    shared 2-core machine here the first demo without data computed its forecasts in 91 s with torch's default two
    threads, 13 s with one). When computing a chunk takes over a second, a progress bar over its frames says so (in the
    main process only, not in vector-env workers; ``progress = False`` turns it off).

    Attributes:
        calls: frames forecast by the predictor in this process (each once when caching).
        chunks_loaded: chunks read from the disk cache.
        chunks_computed: chunks computed here.
        chunks_shared: chunks taken from another source of this process (constant velocity:
            :func:`definition_key`).
        progress: show a progress bar over a chunk's frames when computing it takes over a second.
        threads: torch threads while computing (None: the caller's setting).
    """

    def __init__(
        self,
        name: str,
        predictors: dict[str, ForecastModel],
        default: ForecastModel | None,
        dt_s: float,
        horizon: int,
        cache: bool = True,
        store: ForecastStore | None = None,
    ) -> None:
        self.name = name
        self.memory = "window"
        self.whole_recording = False  # compute_chunks computes one chunk (True: every chunk of the recording)
        self.predictors = predictors
        self.default = default
        self.dt_s = dt_s
        self.horizon = horizon
        self.use_cache = cache
        self.store = store if cache else None
        self._cache: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}
        self._chunks: dict[tuple[str, int], FrameTable] = {}
        self._keys: dict[str, tuple[Recording, TableKey | None]] = {}
        self._shared_keys: dict[str, tuple[Recording, tuple[Any, ...] | None]] = {}
        self._full: dict[str, Replay] = {}
        self._times: dict[str, tuple[Recording, list[float]]] = {}
        self._weights: dict[tuple[float, int, int], np.ndarray] = {}
        self.calls = 0
        self.chunks_loaded = 0
        self.chunks_computed = 0
        self.chunks_shared = 0
        self.progress = True
        self.threads: int | None = 1

    def predictor_for(self, recording: str) -> ForecastModel:
        model = self.predictors.get(recording, self.default)
        if model is None:
            raise ValueError(f"no predictor for recording {recording!r}")
        return model

    def clear_cache(self) -> None:
        """Forget what is held in memory (the disk cache stays)."""
        self._cache.clear()
        self._chunks.clear()
        self._keys.clear()
        self._shared_keys.clear()

    @property
    def cache_size(self) -> int:
        """Annotation frames held in memory."""
        return sum(t.num_frames for t in self._chunks.values())

    # ------------------------------------------------------------------ frames

    def _model_sizes(self, recording: Recording) -> tuple[ForecastModel, int, int]:
        model = self.predictor_for(recording.name)
        return model, int(getattr(model, "obs_len", OBS_LEN)), int(getattr(model, "pred_len", PRED_LEN))

    def _full_replay(self, recording: Recording) -> Replay:
        full = self._full.get(recording.name)
        if full is None or full.recording is not recording:
            full = self._full[recording.name] = Replay(recording)
        return full

    def _history_grid(self, recording: Recording, frames: range, obs_len: int) -> tuple[Replay, np.ndarray, np.ndarray]:
        """``(full replay, positions (F * obs_len, N, 2), presence (F * obs_len, N))`` at the ``obs_len`` annotation
        steps up to each frame's time (frame-major, oldest first) for every pedestrian of the recording."""
        full = self._full_replay(recording)
        back = recording.step_s * np.arange(obs_len - 1, -1, -1)
        times = (full.times[frames.start : frames.stop, None] - back[None, :]).reshape(-1)
        pos, present = full.positions_at(times)
        return full, pos, present

    def _histories(
        self, recording: Recording, frames: range, obs_len: int
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Per frame: ``(seen columns, history (obs_len, n, 2) float32, mask (obs_len, n), present now (n,))``
        from the ``obs_len`` annotation steps up to the frame's time (absent entries are 0)."""
        full, pos, present = self._history_grid(recording, frames, obs_len)
        out = []
        for k in range(len(frames)):
            rows = slice(k * obs_len, (k + 1) * obs_len)
            seen = np.flatnonzero(present[rows].any(axis=0))
            mask = present[rows][:, seen]
            history = pos[rows][:, seen].astype(np.float32)
            history[~mask] = 0.0
            out.append((full.columns[seen], history, mask, mask[-1]))
        return out

    def _checked(self, model: ForecastModel, pred: np.ndarray, n: int, pred_len: int) -> np.ndarray:
        if pred.shape != (n, pred_len, 2):
            raise ValueError(
                f"predictor {getattr(model, 'name', model)!r} returned shape {pred.shape}, expected {(n, pred_len, 2)}"
            )
        return pred

    def compute_frame(self, recording: Recording, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, P, 2) float32)`` at annotation frame ``i`` for the pedestrians present there,
        from the histories of the ``obs_len`` annotation steps up to the frame's time (one predictor call)."""
        model, obs_len, pred_len = self._model_sizes(recording)
        [(cols, history, mask, now)] = self._histories(recording, range(i, i + 1), obs_len)
        if not now.any():
            return np.zeros(0, dtype=np.int64), np.zeros((0, pred_len, 2), np.float32)
        self.calls += 1
        pred = self._checked(model, np.asarray(model.forecast(history, mask)), len(cols), pred_len)
        return cols[now], np.ascontiguousarray(pred[now], dtype=np.float32)

    def compute_chunks(self, recording: Recording, chunk: int) -> dict[int, FrameTable]:
        """Compute chunk ``chunk`` of ``recording`` (a window source needs no other): ``{chunk: table}``; constant
        velocity (:func:`definition_key`): every chunk of the recording, ``{c: table}`` for all ``c``.

        One predictor call per frame, exactly as :meth:`compute_frame`: batching frames together (padded to the
        widest, or even unpadded) changes forecasts in the last float32 bit with the batch's make-up, which would
        let later frames of the chunk change an earlier frame's forecasts (data after t entering the observation
        at t) and make cached forecasts differ from online ones. Constant velocity forecasts each pedestrian from
        its own history alone, so it gets one call per chunk (:meth:`_independent_chunk`), with the same result.
        """
        model, obs_len, pred_len = self._model_sizes(recording)
        if definition_key(model) is not None:  # each pedestrian forecast alone: every chunk, one call each
            return {
                c: self._independent_chunk(model, recording, c, obs_len, pred_len) for c in range(num_chunks(recording))
            }
        parts = []
        frames = chunk_frames(recording, chunk)
        for cols, history, mask, now in self._progress(self._histories(recording, frames, obs_len), recording, frames):
            if not now.any():
                parts.append((np.zeros(0, dtype=np.int64), np.zeros((0, pred_len, 2), np.float32)))
                continue
            self.calls += 1
            pred = self._checked(model, np.asarray(model.forecast(history, mask)), len(cols), pred_len)
            parts.append((cols[now], np.ascontiguousarray(pred[now], dtype=np.float32)))
        return {chunk: FrameTable.from_frames(parts, pred_len)}

    def _independent_chunk(
        self, model: ForecastModel, recording: Recording, chunk: int, obs_len: int, pred_len: int
    ) -> FrameTable:
        """Chunk ``chunk`` in one predictor call for a predictor that forecasts each pedestrian from its own history
        alone (:func:`definition_key`): the histories of the pedestrians present at every frame of the chunk, side by
        side. Each pedestrian's row of the batch is what its frame's own call (:meth:`compute_frame`) gives it, so
        the forecasts are identical, bit for bit (``tests/envs/test_forecast_cache.py``)."""
        frames = chunk_frames(recording, chunk)
        full, pos, present = self._history_grid(recording, frames, obs_len)
        n = present.shape[1]
        pos = pos.reshape(len(frames), obs_len, n, 2)
        present = present.reshape(len(frames), obs_len, n)
        frame_of, rows = np.nonzero(present[:, -1])  # frame by frame, columns ascending within a frame
        counts = np.bincount(frame_of, minlength=len(frames))
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        columns = np.asarray(full.columns[rows], dtype=np.int64)
        if len(rows) == 0:
            return FrameTable(offsets, columns, np.zeros((0, pred_len, 2), np.float32))
        mask = present[frame_of, :, rows].T  # (obs_len, M)
        history = pos[frame_of, :, rows].astype(np.float32).transpose(1, 0, 2)  # (obs_len, M, 2)
        history[~mask] = 0.0
        self.calls += int(np.count_nonzero(counts))
        pred = self._checked(model, np.asarray(model.forecast(history, mask)), len(rows), pred_len)
        return FrameTable(offsets, columns, np.ascontiguousarray(pred, dtype=np.float32))

    def _progress(self, items: Any, recording: Recording, frames: range) -> Any:
        """``items`` (one per frame of ``frames``), behind a labelled progress bar shown if they take over a second
        (:attr:`progress`, main process only)."""
        if not self.progress or multiprocessing.parent_process() is not None:
            return items
        from tqdm.auto import tqdm

        label = f"{self.name} forecasts of {recording.name}, frames {frames.start}-{frames.stop - 1}"
        return tqdm(items, total=len(frames), desc=f"{label} (computed once, then cached)", unit="frame", delay=1.0)

    def _compute_chunks(self, recording: Recording, chunk: int) -> dict[int, FrameTable]:
        """:meth:`compute_chunks` on one torch thread, counted in :attr:`chunks_computed`."""
        with torch_threads(self.threads):
            tables = self.compute_chunks(recording, chunk)
        self.chunks_computed += len(tables)
        return tables

    def table_key(self, recording: Recording) -> TableKey | None:
        """The disk-cache key of ``recording``'s forecasts (None without a store or weights to hash)."""
        held = self._keys.get(recording.name)
        if held is not None and held[0] is recording:
            return held[1]
        if held is not None:  # another recording under the same name: forget the old one's forecasts
            self._chunks = {k: v for k, v in self._chunks.items() if k[0] != recording.name}
            self._cache = {k: v for k, v in self._cache.items() if k[0] != recording.name}
        key = None
        if self.store is not None:
            model, obs_len, pred_len = self._model_sizes(recording)
            digest = predictor_fingerprint(model)
            if digest is not None:
                name = str(getattr(model, "name", self.name))
                key = TableKey(
                    name, digest, recording.name, recording_fingerprint(recording), self.memory, obs_len, pred_len
                )
        self._keys[recording.name] = (recording, key)
        return key

    def _shared_key(self, recording: Recording) -> tuple[Any, ...] | None:
        """The process-wide key of ``recording``'s forecasts by a predictor without weights
        (:func:`definition_key`): ``(definition, recording name, recording fingerprint)``; None for other
        predictors."""
        held = self._shared_keys.get(recording.name)
        if held is not None and held[0] is recording:
            return held[1]
        definition = definition_key(self.predictor_for(recording.name))
        key = None if definition is None else (definition, recording.name, recording_fingerprint(recording))
        self._shared_keys[recording.name] = (recording, key)
        return key

    def chunk(self, recording: Recording, chunk: int) -> FrameTable:
        """Chunk ``chunk`` of the recording's forecasts: from memory, else from the disk cache, else computed (and
        written to the disk cache; other processes wait for it rather than computing it too)."""
        fork_safe_torch()
        key = self.table_key(recording)  # also resets what is held when the recording object changed
        hit = self._chunks.get((recording.name, chunk))
        if hit is not None:
            return hit
        if key is None or self.store is None:
            shared = self._shared_key(recording)
            tables = _SHARED_TABLES.get(shared) if shared is not None else None
            if tables is not None and chunk in tables:
                _SHARED_TABLES.move_to_end(shared)
                self.chunks_shared += len(tables)
            else:
                tables = self._compute_chunks(recording, chunk)
                if shared is not None:
                    _share(shared, tables)
        else:
            loaded = self.store.load(key, chunk, recording, quiet=True)  # files appear atomically: read unlocked
            if loaded is None:
                # whoever holds the lock computes; the others then load (a source computing every chunk at once
                # locks the whole recording, chunk 0's lock, so a process needing another chunk waits for that pass)
                with self.store.locked(key, 0 if self.whole_recording else chunk):
                    loaded = self.store.load(key, chunk, recording)
                    if loaded is None:
                        tables = self._compute_chunks(recording, chunk)
                        for c, table in tables.items():
                            self.store.save(key, c, table)
            if loaded is not None:
                tables = {chunk: loaded}
                self.chunks_loaded += 1
        for c, table in tables.items():
            self._chunks[(recording.name, c)] = table
        return tables[chunk]

    def table(self, recording: Recording) -> int:
        """Make every chunk of the recording available (load or compute); returns the number of frames."""
        for c in range(num_chunks(recording)):
            self.chunk(recording, c)
        return len(recording.frames)

    def frame_forecasts(self, recording: Recording, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, P, 2) float32)`` at annotation frame ``i`` (from the chunk when caching)."""
        if self.use_cache:
            return self.chunk(recording, i // CHUNK_FRAMES).at(i % CHUNK_FRAMES)
        fork_safe_torch()
        with torch_threads(self.threads):
            return self.compute_frame(recording, i)

    # ------------------------------------------------------------------ env times

    def all_forecasts(self, replay: Replay, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Forecasts of every pedestrian perceived at ``t_s``.

        Returns:
            ``(columns (M,), positions (M, H, 2))``: recording columns (ascending) and world
            positions at ``t + h * dt_s``, metres.
        """
        key = (replay.name, time_key(t_s))
        if self.use_cache:
            hit = self._cache.get(key)
            if hit is not None:
                return hit
        out = self._resampled(replay.recording, t_s)
        if self.use_cache:
            self._cache[key] = out
        return out

    def _resampled(self, rec: Recording, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        empty = (np.zeros(0, dtype=np.int64), np.zeros((0, self.horizon, 2)))
        times = self._times.get(rec.name)
        if times is None or times[0] is not rec:
            times = self._times[rec.name] = (rec, rec.times_s().tolist())
        i = bisect.bisect_right(times[1], t_s + TIME_TOL_S) - 1
        if i < 0 or rec.present.shape[1] == 0:
            return empty
        offset = t_s - times[1][i]
        offset = offset if offset > TIME_TOL_S else 0.0
        if offset >= rec.step_s - TIME_TOL_S:
            return empty  # the tracker has dropped every track (an annotation gap, or after the recording)
        cols, fc = self.frame_forecasts(rec, i)
        if len(cols) == 0:
            return empty
        pred_len = fc.shape[1]
        wkey = (float(rec.step_s), pred_len, time_key(offset))
        weights = self._weights.get(wkey)
        if weights is None:
            weights = self._weights[wkey] = resample_matrix(
                float(rec.step_s), self.dt_s, self.horizon, pred_len, offset
            )
        out = weights[:, 1:] @ fc.astype(np.float64)  # (H, P) @ (n, P, 2) -> (n, H, 2)
        if weights[:, 0].any():  # the first env steps fall before the first forecast step: the annotated position
            out += weights[None, :, 0, None] * rec.positions[i, cols][:, None, :]
        return cols, out

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
            raise RuntimeError(f"forecast requested for pedestrians not perceived at t={t_s:.3f} s in {replay.name}")
        return fc[idx]


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
    (j = 1..pred_len, ``tau`` = the frame's time) and is used, as in :class:`PredictorForecast`, at every env
    time whose latest annotation is frame ``i``. The forecaster only ever sees frames up to ``tau``.

    With ``cache=True`` a recording's forecasts at all its frames are computed in one pass on first use
    (replayed pedestrians ignore the robot), and shared through the disk cache like window forecasts.
    With ``cache=False`` (online) a forecaster per recording
    advances frame by frame as the env's time does, restarting from the first frame when an episode goes
    back in time. Both feed the same frames in the same order, so they give identical forecasts. Each step
    of the forecaster computes only the pedestrians present at that frame or the one before.

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
        store: ForecastStore | None = None,
    ) -> None:
        super().__init__(name, predictors, default, dt_s, horizon, cache, store)
        self.memory = "carried"
        self.whole_recording = True
        for model in [*predictors.values(), *([default] if default is not None else [])]:
            if not callable(getattr(model, "online", None)):
                raise ConfigError(
                    f"forecast_memory 'carried' needs a predictor with an online(num_slots) method (hidden states "
                    f"carried between steps); {getattr(model, 'name', model)!r} has none. Use forecast_memory 'window'."
                )
        self._walks: dict[str, _CarriedWalk] = {}

    def clear_cache(self) -> None:
        super().clear_cache()
        self._walks.clear()

    def compute_frame(self, recording: Recording, i: int) -> tuple[np.ndarray, np.ndarray]:
        walk = self._walks.get(recording.name)
        if walk is None or walk.recording is not recording:
            walk = _CarriedWalk(self.predictor_for(recording.name), recording)
            self._walks[recording.name] = walk
        before = walk.calls
        out = walk.at(i)
        self.calls += walk.calls - before
        return out

    def compute_chunks(self, recording: Recording, chunk: int) -> dict[int, FrameTable]:
        """Every chunk of the recording, in one pass of an online forecaster from its first frame (hidden states
        cannot start in the middle)."""
        walk = _CarriedWalk(self.predictor_for(recording.name), recording)
        frames = range(len(recording.frames))
        forecasts = [walk.at(k) for k in self._progress(frames, recording, frames)]
        out = {
            c: FrameTable.from_frames([forecasts[k] for k in chunk_frames(recording, c)], walk.pred_len)
            for c in range(num_chunks(recording))
        }
        self.calls += walk.calls
        return out


# ----------------------------------------------------------------------------- fork safety


#: The process that imported this module; a process with another id is a forked child (or a child's child).
_IMPORT_PID: Final[int] = os.getpid()
#: The forked process that has already been switched to one torch thread.
_ONE_THREAD_PID: int | None = None


def fork_safe_torch() -> None:
    """In a forked child, run torch on one thread from here on; elsewhere nothing.

    A forked process inherits the parent's GNU OpenMP (``libgomp``) state but not its worker threads: once the
    parent has run a parallel torch operation (loading or hashing a predictor, a user's own torch code), the child's
    first parallel operation waits forever for threads that do not exist. Gymnasium's async vector env forks its
    workers, which build their environments and compute forecasts when the cache is cold; every path that runs a
    predictor (:func:`make_forecast_source`, :meth:`PredictorForecast.chunk`, :meth:`PredictorForecast.frame_forecasts`)
    calls this first, so torch never enters an OpenMP region there. A worker of vectorised environments needs one
    thread anyway (as :func:`agents.train.make_env` sets); processes started with ``spawn`` or ``forkserver`` import
    this module afresh and keep their threads. (A fork is recognised by the process id, not by an
    ``os.register_at_fork`` hook: a hook would keep ``sys.modules`` alive into interpreter shutdown, where pymunk's
    spaces must not be freed.)
    """
    global _ONE_THREAD_PID
    pid = os.getpid()
    if pid == _IMPORT_PID or pid == _ONE_THREAD_PID:
        return
    torch = sys.modules.get("torch")
    if torch is not None:  # not imported: the parent had no torch state to inherit
        torch.set_num_threads(1)
    _ONE_THREAD_PID = pid


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run torch on ``n`` threads inside the block and restore the caller's count after (nothing without torch, or
    with ``n`` None)."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None and n is not None else n
    if before == n:
        yield
        return
    torch.set_num_threads(n)  # type: ignore[union-attr]
    try:
        yield
    finally:
        torch.set_num_threads(before)  # type: ignore[union-attr]


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
            shipped = name in LEARNED_SOURCES
            raise PredictorUnavailableError(
                f"the {'pretrained ' if shipped else 'plug-in '}{name!r} predictor for split {split!r} (needed to "
                f"forecast {needed_for}) could not be loaded: {type(exc).__name__}: {str(exc).rstrip('.')}. "
                + (WEIGHTS_HELP if shipped else "See crowdnav_mesrnn.predictors for the plug-in protocol.")
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
    store: ForecastStore | None = None,
) -> ForecastSource:
    """The forecast source for a set of recordings.

    Args:
        predictor: a source name or a predictor object (used for every recording).
        recordings: names of the recordings episodes may replay.
        default_split: split whose predictor forecasts recordings that belong to no split's test
            part (synthetic, scripted crowds).
        dt_s: environment step, seconds.
        horizon: H.
        cache: keep forecasts (per chunk of annotation frames, and resampled per time).
        noisy_oracle_ade_m: target ADE of ``noisy_oracle``.
        memory: ``window`` or ``carried`` (see :attr:`envs.config.CrowdNavConfig.forecast_memory`); ignored by
            ``none``, ``cv``, ``oracle`` and ``noisy_oracle``.
        store: the shared disk cache for predictors with weights (None: memory only).

    Raises:
        ConfigError: ``carried`` with a predictor object (or loaded predictor) without ``online(num_slots)``.
    """
    if memory not in FORECAST_MEMORIES:
        raise ConfigError(f"unknown forecast_memory {memory!r}; valid: {', '.join(FORECAST_MEMORIES)}")
    fork_safe_torch()
    learned_cls = CarriedPredictorForecast if memory == "carried" else PredictorForecast
    if not isinstance(predictor, str):
        if not callable(getattr(predictor, "forecast", None)):
            raise ConfigError(
                f"predictor must be one of {', '.join(FORECAST_SOURCES)} or an object with a forecast(history, mask) "
                f"method, got {predictor!r}"
            )
        return learned_cls(str(getattr(predictor, "name", "custom")), {}, predictor, dt_s, horizon, cache, store)
    if predictor == "none":
        return NoForecast()
    if predictor == "oracle":
        return OracleForecast()
    if predictor == "noisy_oracle":
        return NoisyOracleForecast(noisy_oracle_ade_m, horizon)
    if predictor == "cv":
        from crowdnav_mesrnn.models import get_predictor

        return PredictorForecast("cv", {}, get_predictor("cv"), dt_s, horizon, cache)
    if predictor in LEARNED_SOURCES or is_plugin_source(predictor):  # a plug-in loads per split like MESRNN
        per_recording: dict[str, ForecastModel] = {}
        default: ForecastModel | None = None
        for rec in recordings:
            split = split_of_recording(rec)
            if split is None:
                default = load_learned(predictor, default_split, rec)
            else:
                per_recording[rec] = load_learned(predictor, split, rec)
        return learned_cls(predictor, per_recording, default, dt_s, horizon, cache, store)
    raise ValueError(check_predictor_name(predictor))  # raises ConfigError listing the valid names


# ----------------------------------------------------------------------------- the shared cache, filled ahead

#: Parts accepted by :func:`build_forecast_cache`.
CACHE_PARTS: Final[tuple[str, ...]] = ("train", "test", "all")


def cache_recordings(split: str | None = None, part: str = "all") -> tuple[str, ...]:
    """Recordings whose forecasts an env of ``split``/``part`` may need: ``part="all"`` = train and test;
    ``split=None`` = every replayable recording (the five scenes' held-out recordings)."""
    from envs.config import episode_recordings

    if part not in CACHE_PARTS:
        raise ValueError(f"unknown part {part!r}; valid: {', '.join(CACHE_PARTS)}")
    if split is None:
        return tuple(r for recs in SPLIT_TEST_RECORDINGS.values() for r in recs)
    if split not in SPLIT_TEST_RECORDINGS:
        raise ValueError(f"unknown split {split!r}; valid: {', '.join(SPLIT_TEST_RECORDINGS)}")
    parts = ("train", "test") if part == "all" else (part,)
    return tuple(r for p in parts for r in episode_recordings(split, p))


def build_forecast_cache(
    predictor: str,
    split: str | None = None,
    part: str = "all",
    *,
    memory: str = "window",
    data_dir: str | None = None,
    cache_dir: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Fill the shared disk cache with a learned predictor's forecasts for the recordings an env of ``split``/``part``
    replays (every replayable recording when ``split`` is None), each by its out-of-sample predictor.

    Chunks already on disk are checked and kept; missing, unreadable or stale ones are computed and
    written. Call it before starting vectorised environments or grid workers, so none of them computes forecasts.

    Args:
        predictor: ``mesrnn``, ``srnn`` or ``vlstm``.
        split: leave-one-out split (None: all recordings).
        part: ``train``, ``test`` or ``all``.
        memory: ``window`` or ``carried`` (see ``forecast_memory``).
        data_dir: ETH/UCY folder (default: the usual search).
        cache_dir: cache folder (default: ``$CROWDNAV_MESRNN_CACHE`` or ``~/.cache/crowdnav-mesrnn/forecasts``).
        progress: show a progress bar (tqdm) over chunks.

    Returns:
        ``{"predictor", "memory", "cache_dir", "recordings", "chunks", "loaded", "computed", "seconds"}``.
    """
    import time

    from crowdnav_mesrnn.data.recordings import load_recording
    from envs.forecast_cache import cache_root

    if predictor not in LEARNED_SOURCES and not is_plugin_source(predictor):
        raise ValueError(
            f"unknown predictor {predictor!r} for the forecast cache; valid: {', '.join(LEARNED_SOURCES)}, an installed "
            "predictor plug-in or an import path 'package.module:Factory' (none, cv, oracle and noisy_oracle need no cache)"
        )
    if memory not in FORECAST_MEMORIES:
        raise ValueError(f"unknown forecast memory {memory!r}; valid: {', '.join(FORECAST_MEMORIES)}")
    started = time.perf_counter()
    names = cache_recordings(split, part)
    recordings = [load_recording(n, "all_data", data_dir) for n in names]
    root = cache_root(cache_dir)
    store = ForecastStore(root)
    problem = store.write_problem()
    if problem is not None:
        raise ValueError(f"the forecast cache folder {root} cannot be written ({problem}); choose another one")
    default_split = split if split is not None else "zara1"
    source = make_forecast_source(predictor, list(names), default_split, 0.4, 12, True, 0.0, memory, store)
    assert isinstance(source, PredictorForecast)
    source.progress = False  # this function's own bar counts the chunks
    source.threads = None  # the caller's torch threads (``forecasts build --threads``)
    total = sum(num_chunks(r) for r in recordings)
    bar: Any = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc=f"{predictor} forecasts", unit="chunk")
    for rec in recordings:
        for c in range(num_chunks(rec)):
            source.chunk(rec, c)
            if bar is not None:
                bar.set_postfix_str(rec.name, refresh=False)
                bar.update(1)
    if bar is not None:
        bar.close()
    if store.unwritable is not None:
        raise ValueError(f"the forecast cache folder {root} could not be written ({store.unwritable})")
    return {
        "predictor": predictor,
        "memory": memory,
        "cache_dir": str(root),
        "recordings": list(names),
        "chunks": total,
        "loaded": source.chunks_loaded,
        "computed": source.chunks_computed,
        "seconds": round(time.perf_counter() - started, 2),
    }
