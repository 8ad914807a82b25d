"""Forecasts computed once: the shared on-disk cache, and the tables one process shares between its sources.

Replayed pedestrians ignore the robot, so the forecasts at a recording's annotation frames depend only on
(predictor weights, recording content, the settings that change them). They are stored in chunks of
:data:`CHUNK_FRAMES` frames, one ``.npz`` file each, under ``<root>/<predictor>-<memory>/``, named by the
recording and a digest of a :class:`TableKey`:

- ``predictor_hash``: SHA-256 of the predictor's weights (every tensor of its state dict, with names, dtypes
  and shapes), its normalisation and its model config as saved in checkpoints (:func:`predictor_fingerprint`,
  :func:`config_text`);
- ``recording_hash``: SHA-256 of the recording's annotation times, ids, presence and positions
  (:func:`recording_fingerprint`);
- the settings: forecast memory (``window``/``carried``), ``obs_len``, ``pred_len``, the perception rule
  (:data:`PERCEPTION`), the chunk size and :data:`FORMAT_VERSION` (``carried`` tables also
  :data:`CARRIED_REVISION`).

The environment's ``dt_s`` and ``horizon_steps`` are not part of the key: the files hold the predictor's raw
forecasts on the annotation grid, and their resampling onto ``t + h * dt_s`` happens at lookup.

A chunk is written only when its forecasts pass :func:`crowdnav_mesrnn.predictors.check_forecast` (the promised shape,
finite). Files are written atomically (:func:`crowdnav_mesrnn.utils.atomic_write`) under a per-file lock, so processes
started together (vectorised environments, grid workers) compute each chunk once and the others load it. A file
that cannot be read, or whose stored key or shapes do not match, is reported with a warning and rebuilt.

Root folder: the config key ``forecast_cache_dir``, else ``$CROWDNAV_MESRNN_CACHE``, else
``~/.cache/crowdnav-mesrnn/forecasts``.

Predictors without weights to hash are not written to disk; constant velocity's tables, defined by its code alone
(:func:`definition_key`), are computed once per process and shared by every source in it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import warnings
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn.data.recordings import Recording
from crowdnav_mesrnn.models.base import ConstantVelocity
from crowdnav_mesrnn.predictors import check_forecast
from crowdnav_mesrnn.utils import atomic_write, file_lock

#: Bump when the content or layout of the files changes (old files then no longer match and are rebuilt). Files hold
#: one predictor call per frame (no cross-frame batching), so a chunk equals its frames computed alone.
FORMAT_VERSION: Final[int] = 2
#: Bump when the arithmetic of the online (carried-state) forecast changes, even to float32 rounding; part of the key
#: of ``carried`` tables only, so ``window`` tables are kept.
CARRIED_REVISION: Final[int] = 2
#: How forecasts relate to perception: taken at each annotation frame from the histories up to it.
PERCEPTION: Final[str] = "latest-annotation"
#: Annotation frames per file.
CHUNK_FRAMES: Final[int] = 64
#: Environment variable naming the cache folder.
CACHE_ENV_VAR: Final[str] = "CROWDNAV_MESRNN_CACHE"


class CacheWarning(UserWarning):
    """A cache file was unreadable or stale and is being rebuilt."""


def cache_root(configured: str | os.PathLike[str] | None = None) -> Path:
    """The cache folder: ``configured``, else ``$CROWDNAV_MESRNN_CACHE``, else ``~/.cache/crowdnav-mesrnn/forecasts``."""
    if configured is not None:
        return Path(configured).expanduser()
    env = os.environ.get(CACHE_ENV_VAR)
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "crowdnav-mesrnn" / "forecasts"


def config_text(config: Any) -> str:
    """The text a predictor's model config enters its cache key as.

    It is built from ``config.to_dict()`` (the config as saved in checkpoints), never from the config's repr, so how
    a config prints changes no key. It reads ``ModelConfig(model='mesrnn', node_embed=128, ...)``: the class name,
    then every entry of ``to_dict()`` in order as ``key=value`` with Python literals (lists as tuples), the text the
    keys have hashed since the cache exists, so files written before stay valid. A config without ``to_dict`` enters
    by its repr, and None as ``None``.
    """
    to_dict = getattr(config, "to_dict", None)
    if not callable(to_dict):
        return repr(config)
    entries = ", ".join(f"{key}={_literal(value)!r}" for key, value in to_dict().items())
    return f"{type(config).__name__}({entries})"


def _literal(value: Any) -> Any:
    """``value`` with its lists turned into tuples, recursively (how a frozen config holds them)."""
    if isinstance(value, list | tuple):
        return tuple(_literal(v) for v in value)
    if isinstance(value, dict):
        return {k: _literal(v) for k, v in value.items()}
    return value


_FINGERPRINTS: dict[int, tuple[Any, str | None]] = {}


def predictor_fingerprint(model: Any) -> str | None:
    """SHA-256 of a predictor's weights, normalisation and config; None when it has none to hash.

    A predictor object may define ``cache_fingerprint() -> str`` itself; otherwise one with a torch ``net``
    and a ``norm`` (:class:`crowdnav_mesrnn.models.learned.LearnedPredictor`) is hashed. A plug-in loaded by name
    (:func:`crowdnav_mesrnn.predictors.load`) is keyed on its identity (name, target, distribution version, every
    file of the plug-in: :mod:`crowdnav_mesrnn.plugin_files`) plus that digest, so it is disk-cached even without
    weights, and any change to its files recomputes its forecasts. Any other object (constant velocity,
    test doubles passed as objects) is not disk-cached.
    """
    held = _FINGERPRINTS.get(id(model))
    if held is not None and held[0] is model:
        return held[1]
    custom = getattr(model, "cache_fingerprint", None)
    net, norm = getattr(model, "net", None), getattr(model, "norm", None)
    from crowdnav_mesrnn.predictors import identity_of

    plugin = identity_of(model)  # a plug-in loaded by name: its identity + (below) its weights or own digest
    if callable(custom):
        digest: str | None = str(custom())
    elif net is not None and callable(getattr(net, "state_dict", None)) and norm is not None:
        h = hashlib.sha256()
        head = [
            type(model).__qualname__,
            getattr(model, "name", ""),
            getattr(model, "obs_len", ""),
            getattr(model, "pred_len", ""),
        ]
        h.update(f"({head!r}, {config_text(getattr(net, 'cfg', None))})".encode())
        for name, tensor in sorted(net.state_dict().items()):
            arr = np.ascontiguousarray(tensor.detach().cpu().numpy())
            h.update(f"{name}:{arr.dtype}:{arr.shape}".encode())
            h.update(memoryview(arr).cast("B"))
        for name, value in sorted(vars(norm).items()):
            h.update(f"{name}:".encode())
            h.update(np.asarray(value, dtype=np.float64).tobytes())
        digest = h.hexdigest()
    else:
        digest = None
    if plugin is not None:
        digest = hashlib.sha256(f"plugin:{plugin}:{digest or ''}".encode()).hexdigest()
    _FINGERPRINTS[id(model)] = (model, digest)
    return digest


def recording_fingerprint(recording: Recording) -> str:
    """SHA-256 of a recording's content: step, frames, ids, presence and the positions where present."""
    h = hashlib.sha256()
    h.update(repr(float(recording.step_s)).encode())
    present = np.ascontiguousarray(recording.present, dtype=bool)
    for arr in (recording.frames, recording.ped_ids, np.packbits(present), recording.positions[present]):
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype}:{a.shape}:{present.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


@dataclass(frozen=True)
class TableKey:
    """What a recording's forecasts depend on (see the module docstring)."""

    predictor: str
    predictor_hash: str
    recording: str
    recording_hash: str
    memory: str
    obs_len: int
    pred_len: int

    def meta(self) -> dict[str, Any]:
        """The key plus the fixed settings, as stored in every file (``carried`` tables: and
        :data:`CARRIED_REVISION`)."""
        meta = {
            **asdict(self),
            "format": FORMAT_VERSION,
            "perception": PERCEPTION,
            "chunk_frames": CHUNK_FRAMES,
        }
        if self.memory == "carried":
            meta["carried_revision"] = CARRIED_REVISION
        return meta

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.meta(), sort_keys=True).encode()).hexdigest()[:20]


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "_"


@dataclass(frozen=True)
class FrameTable:
    """Forecasts at consecutive annotation frames of a recording (one chunk, or a whole recording).

    Attributes:
        offsets: ``(F + 1,)``: the entries of the table's frame ``i`` are ``offsets[i]:offsets[i + 1]``.
        columns: ``(M,)`` recording columns of the pedestrians present at each frame, ascending per frame.
        forecasts: ``(M, P, 2)`` float32 metres at ``tau_i + j * step_s`` (j = 1..P), ``tau_i`` the frame's time.
    """

    offsets: np.ndarray
    columns: np.ndarray
    forecasts: np.ndarray

    @classmethod
    def from_frames(cls, parts: list[tuple[np.ndarray, np.ndarray]], pred_len: int) -> FrameTable:
        """From ``[(columns (n_i,), forecasts (n_i, P, 2)), ...]``, one per frame in order."""
        sizes = np.array([len(c) for c, _ in parts], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        cols = np.concatenate([c for c, _ in parts]).astype(np.int64) if parts else np.zeros(0, np.int64)
        fcs = (
            np.concatenate([f for _, f in parts]).astype(np.float32)
            if parts
            else np.zeros((0, pred_len, 2), np.float32)
        )
        return cls(offsets, cols, fcs)

    @property
    def num_frames(self) -> int:
        return len(self.offsets) - 1

    def at(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(columns (n,), forecasts (n, P, 2))`` of the table's frame ``i``."""
        a, b = self.offsets[i], self.offsets[i + 1]
        return self.columns[a:b], self.forecasts[a:b]


class ForecastStore:
    """Chunk files of forecasts under ``root`` (see the module docstring).

    Args:
        root: the cache folder (created when the first file is written).
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        #: why the folder cannot be written (None: writable so far); once set, nothing more is written
        self.unwritable: str | None = None

    def write_problem(self) -> str | None:
        """Why files cannot be written into the folder (created if missing), or None when they can."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=self.root):
                pass
        except OSError as exc:
            return f"{type(exc).__name__}: {exc}"
        return None

    def _cannot_write(self, exc: OSError) -> None:
        """Warn once that the folder cannot be written; from then on forecasts stay in memory."""
        if self.unwritable is None:
            self.unwritable = f"{type(exc).__name__}: {exc}"
            warnings.warn(
                f"forecast cache folder {self.root} cannot be written ({self.unwritable}); this process computes "
                f"its forecasts and keeps them in memory only (set forecast_cache_dir or ${CACHE_ENV_VAR} to a "
                "writable folder to share them)",
                CacheWarning,
                stacklevel=5,
            )

    def path(self, key: TableKey, chunk: int) -> Path:
        folder = self.root / f"{_safe(key.predictor)}-{_safe(key.memory)}"
        return folder / f"{_safe(key.recording)}-{key.digest()}-c{chunk:04d}.npz"

    @contextlib.contextmanager
    def locked(self, key: TableKey, chunk: int) -> Iterator[None]:
        """Hold an exclusive lock on one chunk (so concurrent processes compute it once); a no-op where file
        locks are unavailable, and (after one :class:`CacheWarning`) where the folder cannot be written."""
        path = self.path(key, chunk)
        with contextlib.ExitStack() as stack:
            if self.unwritable is None:
                try:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    stack.enter_context(file_lock(path.with_name(path.name + ".lock")))
                except OSError as exc:
                    self._cannot_write(exc)
            yield

    def load(self, key: TableKey, chunk: int, recording: Recording, quiet: bool = False) -> FrameTable | None:
        """The chunk, or None when it is missing; an unreadable or stale file gives a :class:`CacheWarning`
        (unless ``quiet``) and None (the caller rebuilds and overwrites it)."""
        path = self.path(key, chunk)
        if not path.is_file():
            return None
        warn = (lambda path, problem: None) if quiet else self._warn
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                out = FrameTable(data["offsets"], data["columns"], data["forecasts"])
        except Exception as exc:  # any unreadable file is rebuilt the same way
            warn(path, f"unreadable ({type(exc).__name__}: {exc})")
            return None
        if meta != key.meta():
            changed = sorted(k for k in set(meta) | set(key.meta()) if meta.get(k) != key.meta().get(k))
            warn(path, f"stale (stored key differs in {', '.join(changed)})")
            return None
        problem = check_chunk(out, recording, chunk, key.pred_len)
        if problem is not None:
            warn(path, problem)
            return None
        return out

    def save(self, key: TableKey, chunk: int, data: FrameTable) -> Path | None:
        """Write one chunk atomically; None (after one :class:`CacheWarning`) when the folder cannot be written.

        Raises:
            crowdnav_mesrnn.predictors.ForecastError: the chunk's forecasts are not ``(M, pred_len, 2)`` or not
                finite (:func:`~crowdnav_mesrnn.predictors.check_forecast`); nothing is written.
        """
        row_frames = chunk * CHUNK_FRAMES + np.repeat(np.arange(data.num_frames), np.diff(data.offsets))
        check_forecast(
            data.forecasts,
            name=key.predictor,
            expected_shape=(len(data.columns), key.pred_len, 2),
            recording=key.recording,
            frame=row_frames,
        )
        if self.unwritable is not None:
            return None
        meta = np.array(json.dumps(key.meta(), sort_keys=True))

        def write(fh: Any) -> None:
            np.savez(fh, meta=meta, offsets=data.offsets, columns=data.columns, forecasts=data.forecasts)

        try:
            return atomic_write(self.path(key, chunk), write)
        except OSError as exc:  # read-only, full, or not a folder: keep going in memory
            self._cannot_write(exc)
            return None

    @staticmethod
    def _warn(path: Path, problem: str) -> None:
        warnings.warn(f"forecast cache file {path} is {problem}; rebuilding it", CacheWarning, stacklevel=4)


def chunk_frames(recording: Recording, chunk: int) -> range:
    """The recording's annotation frames held in ``chunk``."""
    return range(chunk * CHUNK_FRAMES, min((chunk + 1) * CHUNK_FRAMES, len(recording.frames)))


def num_chunks(recording: Recording) -> int:
    return -(-len(recording.frames) // CHUNK_FRAMES)


def check_chunk(data: FrameTable, recording: Recording, chunk: int, pred_len: int) -> str | None:
    """What is wrong with a chunk of ``recording`` (shapes, dtypes, finiteness, exactly the pedestrians present at
    each frame, ascending), or None."""
    frames = chunk_frames(recording, chunk)
    off, cols, fc = data.offsets, data.columns, data.forecasts
    if off.shape != (len(frames) + 1,) or off.dtype.kind != "i" or cols.ndim != 1 or cols.dtype.kind != "i":
        return f"malformed (offsets {off.shape}, columns {cols.shape}, {len(frames)} frames expected)"
    if fc.dtype != np.float32 or fc.shape != (len(cols), pred_len, 2):
        return f"malformed (forecasts {fc.dtype} {fc.shape}, expected float32 ({len(cols)}, {pred_len}, 2))"
    present = recording.present[frames.start : frames.stop]
    counts = np.diff(off)
    if off[0] != 0 or off[-1] != len(cols) or not np.array_equal(counts, present.sum(axis=1)):
        return "inconsistent with the recording (pedestrians per frame differ)"
    if len(cols):
        if cols.min() < 0 or cols.max() >= present.shape[1]:
            return "inconsistent with the recording (column out of range)"
        frame_of = np.repeat(np.arange(len(frames)), counts)
        if not present[frame_of, cols].all():
            return "inconsistent with the recording (a forecast for an absent pedestrian)"
        if not np.isfinite(fc).all():
            return "corrupt (non-finite forecasts)"
    return None


def describe(root: str | os.PathLike[str] | None = None) -> list[dict[str, Any]]:
    """What is cached under ``root``: one row per (predictor-memory folder, recording, key digest) with the
    number of chunk files and their total size in bytes."""
    base = cache_root(root)
    rows: dict[tuple[str, str, str], dict[str, Any]] = {}
    if not base.is_dir():
        return []
    for path in sorted(base.glob("*/*.npz")):
        parts = path.stem.rsplit("-", 2)  # <recording>-<digest>-cNNNN
        if len(parts) != 3 or len(parts[1]) != 20 or not parts[2].startswith("c"):
            continue  # not a chunk file of this cache
        recording, digest, _ = parts
        row = rows.setdefault(
            (path.parent.name, recording, digest),
            {"source": path.parent.name, "recording": recording, "key": digest, "chunks": 0, "bytes": 0},
        )
        row["chunks"] += 1
        row["bytes"] += path.stat().st_size
    return list(rows.values())


# ----------------------------------------------------------------------------- the process-wide tables

#: Recordings whose forecasts by a predictor without weights (:func:`definition_key`) this process keeps, shared by
#: every source (the environments of a vectorised env, a grid cell's warm start, training and validation).
SHARED_RECORDINGS: Final[int] = 64
_SHARED_TABLES: OrderedDict[tuple[Any, ...], dict[int, FrameTable]] = OrderedDict()


def definition_key(model: Any) -> tuple[Any, ...] | None:
    """What determines the forecasts of a predictor defined by its code alone, or None for any other.

    Only :class:`~crowdnav_mesrnn.models.ConstantVelocity` itself (not a subclass, which may forecast otherwise)
    qualifies: it has no weights and forecasts each pedestrian from its own history alone, so its forecasts of a
    recording depend on ``(obs_len, pred_len)`` and the recording's content.
    :class:`~envs.forecasting.window.PredictorForecast` then computes a recording's whole table at once, each chunk in
    one call (:meth:`~envs.forecasting.window.PredictorForecast._independent_chunk`), and shares it with every
    other source of the process instead of each environment computing its own. They are not written to the disk
    cache, whose key would then have to hash this code rather than weights; a process computes a recording's table
    once.
    """
    if type(model) is ConstantVelocity:
        return ("ConstantVelocity", int(model.obs_len), int(model.pred_len))
    return None


def _share(key: tuple[Any, ...], tables: dict[int, FrameTable]) -> None:
    """Keep ``tables`` for the process under ``key`` (the least recently used recording beyond
    :data:`SHARED_RECORDINGS` is forgotten). Their arrays are made read-only: every source of the process hands out
    views of them (:meth:`~envs.forecasting.window.PredictorForecast.frame_forecasts`), so a caller writing into one
    would change the forecasts of every other environment."""
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
