"""Sliding windows of 8 observed + 12 future annotation steps, with context pedestrians."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.recordings import Recording, load_split


@dataclass(frozen=True)
class Window:
    """One window of ``T = obs_len + pred_len`` consecutive annotation frames.

    Attributes:
        positions: ``(T, N, 2)`` float32 metres, 0 where absent.
        present: ``(T, N)`` bool presence mask.
        scored: ``(N,)`` bool, pedestrians present in all ``T`` frames (the ones scored by ADE/FDE).
            The others are context: present in at least one frame of the window.
        recording: name of the recording the window was cut from.
        start_frame: frame number of the first observed step.
        ped_ids: ``(N,)`` pedestrian ids in the recording.
    """

    positions: np.ndarray
    present: np.ndarray
    scored: np.ndarray
    recording: str
    start_frame: int
    ped_ids: np.ndarray

    @property
    def num_scored(self) -> int:
        return int(self.scored.sum())

    @property
    def num_peds(self) -> int:
        return int(self.present.shape[1])


def windows_from_recording(
    rec: Recording, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN, min_scored: int = 1
) -> list[Window]:
    """Slide a window by one annotation over the recording's sorted unique frames.

    Every pedestrian present in any of the window's frames is kept (scored or context); a
    window is kept when it has at least ``min_scored`` scored pedestrians.
    """
    seq = obs_len + pred_len
    out: list[Window] = []
    for start in range(len(rec.frames) - seq + 1):
        pres = rec.present[start : start + seq]
        cols = np.flatnonzero(pres.any(axis=0))
        scored = pres[:, cols].all(axis=0)
        if scored.sum() < min_scored:
            continue
        out.append(
            Window(
                positions=rec.positions[start : start + seq, cols].astype(np.float32),
                present=pres[:, cols].copy(),
                scored=scored,
                recording=rec.name,
                start_frame=int(rec.frames[start]),
                ped_ids=rec.ped_ids[cols],
            )
        )
    return out


def split_windows(
    split: str,
    part: str,
    min_scored: int = 1,
    data_dir: str | os.PathLike[str] | None = None,
    obs_len: int = OBS_LEN,
    pred_len: int = PRED_LEN,
) -> list[Window]:
    """All windows of one part of a split (windows never cross files)."""
    out: list[Window] = []
    for rec in load_split(split, part, data_dir):
        out.extend(windows_from_recording(rec, obs_len, pred_len, min_scored))
    return out


def collate(windows: Sequence[Window]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pad windows into one batch.

    Returns:
        positions ``(B, T, N, 2)`` float32 metres (0 where padded or absent),
        present ``(B, T, N)`` bool, scored ``(B, N)`` bool, with ``N`` the largest window.
    """
    if not windows:
        raise ValueError("cannot collate an empty list of windows")
    t = windows[0].positions.shape[0]
    n = max(w.num_peds for w in windows)
    b = len(windows)
    pos = np.zeros((b, t, n, 2), dtype=np.float32)
    pres = np.zeros((b, t, n), dtype=bool)
    scored = np.zeros((b, n), dtype=bool)
    for i, w in enumerate(windows):
        k = w.num_peds
        pos[i, :, :k] = w.positions
        pres[i, :, :k] = w.present
        scored[i, :k] = w.scored
    return pos, pres, scored


def window_locator(windows: Sequence[Window]) -> Callable[[np.ndarray, np.ndarray], dict[str, str]]:
    """Where a window of a :func:`collate` batch was cut from, for messages naming it.

    Returns:
        A function of one batch entry's positions ``(T, N, 2)`` and presence ``(T, N)`` (as padded by
        :func:`collate`) returning ``{"recording": name, "frame": label}`` of the window of ``windows`` it is (the
        keywords of :func:`crowdnav_mesrnn.predictors.check_forecast`), or ``{"recording": "an unknown window",
        "frame": "?"}``.
    """
    places = {_content(w.positions, w.present): w for w in windows}

    def locate(positions: np.ndarray, present: np.ndarray) -> dict[str, str]:
        seen = np.flatnonzero(np.asarray(present).any(axis=0))
        k = int(seen[-1]) + 1 if len(seen) else 0
        w = places.get(_content(np.asarray(positions)[:, :k], np.asarray(present)[:, :k]))
        if w is None:
            return {"recording": "an unknown window", "frame": "?"}
        return {"recording": w.recording, "frame": f"{w.start_frame} (the window's first observed step)"}

    return locate


def _content(positions: np.ndarray, present: np.ndarray) -> bytes:
    return np.ascontiguousarray(present, dtype=bool).tobytes() + np.ascontiguousarray(positions, np.float32).tobytes()


def all_positions(windows: Iterable[Window]) -> np.ndarray:
    """``(M, 2)`` every present position in the windows (for fitting normalisation)."""
    parts = [w.positions[w.present] for w in windows]
    return np.concatenate(parts, axis=0) if parts else np.zeros((0, 2), np.float32)
