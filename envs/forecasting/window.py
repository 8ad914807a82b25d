"""Window forecasts of a trajectory predictor: at every annotation frame, a fresh rollout from the histories of the
last ``obs_len`` annotation steps (``forecast_memory="window"``, the evaluated protocol).

Forecasts are causal: at env time ``t`` they come from the latest annotation at or before ``t`` (the one the
robot perceives), and are resampled onto the environment's grid (:mod:`envs.forecasting.resampling`). Replayed
pedestrians ignore the robot, so forecasts depend only on (predictor, recording, annotation frame): a
recording's forecasts form :class:`~envs.forecasting.cache.FrameTable` chunks, kept in memory and in the shared
disk cache (:mod:`envs.forecasting.cache`), and a forecast taken from them is identical, bit for bit, to one
computed online.
"""

from __future__ import annotations

import bisect
import multiprocessing
from typing import Any

import numpy as np

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.predictors import check_forecast, label_of
from envs.forecasting.cache import (
    _SHARED_TABLES,
    CHUNK_FRAMES,
    ForecastStore,
    FrameTable,
    TableKey,
    _share,
    chunk_frames,
    definition_key,
    num_chunks,
    predictor_fingerprint,
    recording_fingerprint,
)
from envs.forecasting.resampling import resample_matrix, time_key
from envs.forecasting.sources import ForecastModel, ForecastSource, TrueFuture
from envs.forecasting.threads import FORECAST_THREADS, fork_safe_torch, torch_threads
from envs.replay import TIME_TOL_S, Replay


class PredictorForecast(ForecastSource):
    """Forecasts of a trajectory predictor (``forecast(history (8, N, 2), mask (8, N)) -> (N, 12, 2)``), causal.

    At env time ``t`` the robot perceives the latest annotation at or before ``t`` (time ``tau``; see
    :meth:`envs.replay.Replay.perceived_at`), and its forecasts come from that same annotation: the predictor
    sees the histories of the last ``obs_len`` annotation steps up to ``tau`` (sampled every ``step_s``), and its
    forecast on the annotation grid ``tau + j * step_s`` is resampled linearly onto ``t + h * dt_s`` (the
    interpolation shifted by ``t - tau``, non-zero between ``biwi_eth`` annotations). Nothing annotated after
    ``tau`` enters.

    Forecasts therefore depend only on (predictor, recording, annotation frame). With ``cache=True`` they are
    kept per chunk of :data:`~envs.forecasting.cache.CHUNK_FRAMES` frames (:class:`FrameTable`): a chunk is loaded
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
            (:func:`~envs.forecasting.cache.predictor_fingerprint`) are kept in memory only; constant velocity's
            tables are shared by every source of the process (:func:`~envs.forecasting.cache.definition_key`).

    Computing runs torch on :attr:`threads` threads, :data:`~envs.forecasting.threads.FORECAST_THREADS` (one) by
    default (:func:`~envs.forecasting.threads.torch_threads`; the caller's setting is restored after): a frame's
    batched operations are small, more threads contend for the cores, and they change the forecasts' last bits. When computing a chunk takes over a second, a progress bar over its frames says so (in the main
    process only, not in vector-env workers; ``progress = False`` turns it off).

    Attributes:
        calls: frames forecast by the predictor in this process (each once when caching).
        chunks_loaded: chunks read from the disk cache.
        chunks_computed: chunks computed here.
        chunks_shared: chunks taken from another source of this process (constant velocity:
            :func:`definition_key`).
        progress: show a progress bar over a chunk's frames when computing it takes over a second.
        threads: torch threads while computing (None: the caller's setting, whose forecasts may differ in the last
            bits from the cached ones).
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
        self.threads: int | None = FORECAST_THREADS

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

    def _checked(
        self, model: ForecastModel, pred: Any, n: int, pred_len: int, recording: Recording, frame: Any, rows: Any
    ) -> np.ndarray:
        """``pred`` once :func:`~crowdnav_mesrnn.predictors.check_forecast` has accepted it: ``(n, pred_len, 2)``,
        finite in ``rows`` (the pedestrians present at the frame); ``frame``: the annotation frame, or ``(n,)`` each
        row's frame."""
        return check_forecast(
            pred,
            name=label_of(model),
            expected_shape=(n, pred_len, 2),
            recording=recording.name,
            frame=frame,
            time_s=recording.times_s()[frame],
            rows=rows,
        )

    def compute_frame(self, recording: Recording, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, P, 2) float32)`` at annotation frame ``i`` for the pedestrians present there,
        from the histories of the ``obs_len`` annotation steps up to the frame's time (one predictor call)."""
        model, obs_len, pred_len = self._model_sizes(recording)
        [(cols, history, mask, now)] = self._histories(recording, range(i, i + 1), obs_len)
        if not now.any():
            return np.zeros(0, dtype=np.int64), np.zeros((0, pred_len, 2), np.float32)
        self.calls += 1
        pred = self._checked(model, model.forecast(history, mask), len(cols), pred_len, recording, i, now)
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
        histories = self._histories(recording, frames, obs_len)
        for i, (cols, history, mask, now) in zip(frames, self._progress(histories, recording, frames), strict=True):
            if not now.any():
                parts.append((np.zeros(0, dtype=np.int64), np.zeros((0, pred_len, 2), np.float32)))
                continue
            self.calls += 1
            pred = self._checked(model, model.forecast(history, mask), len(cols), pred_len, recording, i, now)
            parts.append((cols[now], np.ascontiguousarray(pred[now], dtype=np.float32)))
        return {chunk: FrameTable.from_frames(parts, pred_len)}

    def _independent_chunk(
        self, model: ForecastModel, recording: Recording, chunk: int, obs_len: int, pred_len: int
    ) -> FrameTable:
        """Chunk ``chunk`` in one predictor call for a predictor that forecasts each pedestrian from its own history
        alone (:func:`definition_key`): the histories of the pedestrians present at every frame of the chunk, side by
        side. Each pedestrian's row of the batch is what its frame's own call (:meth:`compute_frame`) gives it, so
        the forecasts are identical, bit for bit (``tests/envs/forecasting/test_cache.py``)."""
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
        row_frames = frames.start + frame_of
        pred = self._checked(model, model.forecast(history, mask), len(rows), pred_len, recording, row_frames, None)
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

    def all_forecasts(
        self, replay: Replay, t_s: float, shared: dict[Any, Any] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Forecasts of every pedestrian perceived at ``t_s``.

        Args:
            shared: a table of resampled forecasts kept by the caller for several copies of this source (the batched
                environment's worlds, each with memo tables of its own): a copy that misses its own memo takes the
                forecasts another copy resampled from the same inputs (recording, annotation frame, and resampling
                weights equal bit for bit), so every copy gets what it would compute alone. Only with the cache on.

        Returns:
            ``(columns (M,), positions (M, H, 2))``: recording columns (ascending) and world
            positions at ``t + h * dt_s``, metres.
        """
        key = (replay.name, time_key(t_s))
        if self.use_cache:
            hit = self._cache.get(key)
            if hit is not None:
                return hit
        out = self._resampled(replay.recording, t_s, shared if self.use_cache else None)
        if self.use_cache:
            self._cache[key] = out
        return out

    def frame_at(self, rec: Recording, t_s: float) -> tuple[int, float] | None:
        """``(i, offset_s)``: the annotation frame ``i`` perceived at ``t_s`` (the latest at or before it) and how long
        before ``t_s`` it was; None before the first, or when every track has been dropped (an annotation gap, or after
        the recording)."""
        times = self._times.get(rec.name)
        if times is None or times[0] is not rec:
            times = self._times[rec.name] = (rec, rec.times_s().tolist())
        i = bisect.bisect_right(times[1], t_s + TIME_TOL_S) - 1
        if i < 0 or rec.present.shape[1] == 0:
            return None
        offset = t_s - times[1][i]
        offset = offset if offset > TIME_TOL_S else 0.0
        if offset >= rec.step_s - TIME_TOL_S:
            return None
        return i, offset

    def resample_weights(self, step_s: float, pred_len: int, offset_s: float) -> np.ndarray:
        """The ``(H, pred_len + 1)`` matrix from the annotation grid onto the env's (:func:`resample_matrix`), kept."""
        wkey = (float(step_s), pred_len, time_key(offset_s))
        weights = self._weights.get(wkey)
        if weights is None:
            weights = self._weights[wkey] = resample_matrix(float(step_s), self.dt_s, self.horizon, pred_len, offset_s)
        return weights

    def _resampled(
        self, rec: Recording, t_s: float, shared: dict[Any, Any] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        at = self.frame_at(rec, t_s)
        if at is None:
            return np.zeros(0, dtype=np.int64), np.zeros((0, self.horizon, 2))
        i, offset = at
        # another copy's forecasts of the frame when its weights equal this copy's (a frame with forecasts has its
        # forecast length under (name, i) once a copy resampled it, so this copy's weights are the ones used below)
        pred_len = shared.get((rec.name, i)) if shared is not None else None
        if shared is not None and pred_len is not None:
            hit = shared.get((rec.name, i, self.resample_weights(rec.step_s, pred_len, offset).tobytes()))
            if hit is not None:
                return hit
        cols, fc = self.frame_forecasts(rec, i)
        if len(cols) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, self.horizon, 2))
        weights = self.resample_weights(rec.step_s, fc.shape[1], offset)
        out = weights[:, 1:] @ fc.astype(np.float64)  # (H, P) @ (n, P, 2) -> (n, H, 2)
        if weights[:, 0].any():  # the first env steps fall before the first forecast step: the annotated position
            out += weights[None, :, 0, None] * rec.positions[i, cols][:, None, :]
        if shared is not None:
            shared[(rec.name, i)] = fc.shape[1]
            shared[(rec.name, i, weights.tobytes())] = (cols, out)
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
