"""Reading SGAN-format ETH/UCY files into dense per-recording arrays."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from crowdnav_mesrnn.data.constants import ETH_UCY_DT_S, FRAME_STEP, STEP_S, split_recordings
from crowdnav_mesrnn.data.paths import find_data_dir


class DataFormatError(ValueError):
    """A data file is malformed; the message starts with ``file:line:``."""


@dataclass(frozen=True)
class Recording:
    """One ETH/UCY file as dense arrays.

    Attributes:
        name: file stem, e.g. ``"crowds_zara01"`` or ``"crowds_zara01_train"``.
        path: the file read.
        step_s: seconds per annotation step (0.667 for ``biwi_eth``, 0.4 otherwise).
        frames: ``(F,)`` int64 sorted unique frame numbers.
        ped_ids: ``(P,)`` int64 pedestrian ids, sorted.
        positions: ``(F, P, 2)`` float64 metres, world frame; 0 where absent.
        present: ``(F, P)`` bool, True where the file has a row for (frame, pedestrian).
    """

    name: str
    path: Path
    step_s: float
    frames: np.ndarray
    ped_ids: np.ndarray
    positions: np.ndarray
    present: np.ndarray

    @property
    def base_name(self) -> str:
        """The recording's name without a ``_train``/``_val`` suffix."""
        for suffix in ("_train", "_val"):
            if self.name.endswith(suffix):
                return self.name[: -len(suffix)]
        return self.name

    @property
    def num_rows(self) -> int:
        return int(self.present.sum())

    def times_s(self) -> np.ndarray:
        """``(F,)`` seconds of each frame, from frame numbers (gaps in annotation are real time)."""
        return (self.frames - self.frames[0]) / FRAME_STEP * self.step_s


def parse_file(path: str | os.PathLike[str], step_s: float | None = None) -> Recording:
    """Read one SGAN-format file (``frame  ped_id  x  y`` per line, whitespace separated).

    Raises:
        DataFormatError: naming file and line for a wrong column count, a non-numeric value,
            a NaN or infinite coordinate, a non-integer frame or id, a duplicated
            (frame, pedestrian) row, or an empty file.
    """
    path = Path(path)
    name = path.stem
    rows: list[tuple[int, int, float, float]] = []
    seen: dict[tuple[int, int], int] = {}
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) != 4:
                raise DataFormatError(
                    f"{path}:{lineno}: expected 4 columns (frame, pedestrian_id, x, y), got {len(fields)}: {line.strip()!r}"
                )
            try:
                values = [float(v) for v in fields]
            except ValueError:
                raise DataFormatError(f"{path}:{lineno}: non-numeric value in {line.strip()!r}") from None
            frame, pid, x, y = values
            if not all(math.isfinite(v) for v in values):
                raise DataFormatError(f"{path}:{lineno}: NaN or infinite value in {line.strip()!r}")
            if frame != int(frame) or pid != int(pid):
                raise DataFormatError(
                    f"{path}:{lineno}: frame and pedestrian id must be integers, got {line.strip()!r}"
                )
            key = (int(frame), int(pid))
            if key in seen:
                raise DataFormatError(
                    f"{path}:{lineno}: duplicated row for frame {key[0]}, pedestrian {key[1]} (first at line {seen[key]})"
                )
            seen[key] = lineno
            rows.append((key[0], key[1], x, y))
    if not rows:
        raise DataFormatError(f"{path}:1: empty file (no observations)")
    arr = np.asarray(rows, dtype=np.float64)
    frames, frame_idx = np.unique(arr[:, 0].astype(np.int64), return_inverse=True)
    ped_ids, ped_idx = np.unique(arr[:, 1].astype(np.int64), return_inverse=True)
    positions = np.zeros((len(frames), len(ped_ids), 2), dtype=np.float64)
    present = np.zeros((len(frames), len(ped_ids)), dtype=bool)
    positions[frame_idx, ped_idx] = arr[:, 2:4]
    present[frame_idx, ped_idx] = True
    if step_s is None:
        base = name.removesuffix("_train").removesuffix("_val")
        step_s = STEP_S.get(base, ETH_UCY_DT_S)
    return Recording(name, path, float(step_s), frames, ped_ids, positions, present)


@lru_cache(maxsize=64)
def _load_cached(path: str, mtime_ns: int) -> Recording:
    return parse_file(path)


def load_recording(name: str, part: str = "all_data", data_dir: str | os.PathLike[str] | None = None) -> Recording:
    """Load a recording by name from ``all_data`` (whole file), ``train`` or ``val`` (its pieces).

    Results are cached per file path and modification time.
    """
    root = find_data_dir(data_dir)
    if part == "all_data":
        path = root / "all_data" / f"{name}.txt"
    elif part in ("train", "val"):
        path = root / part / f"{name}_{part}.txt"
    else:
        raise ValueError(f"unknown part folder {part!r}; valid: all_data, train, val")
    if not path.is_file():
        raise FileNotFoundError(f"missing data file {path}")
    return _load_cached(str(path), path.stat().st_mtime_ns)


def load_split(split: str, part: str, data_dir: str | os.PathLike[str] | None = None) -> list[Recording]:
    """The recordings of one part (``train``, ``val`` or ``test``) of a leave-one-out split."""
    return [load_recording(name, folder, data_dir) for name, folder in split_recordings(split, part)]
