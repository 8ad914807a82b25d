"""Crowds as recordings: dense arrays, scripted pedestrians for tests, an empty scene and a synthetic
social-force crowd. Every crowd is a :class:`~crowdnav_mesrnn.data.Recording` (frames x pedestrians, metres,
seconds per annotation step), like the ETH/UCY files (:func:`crowdnav_mesrnn.data.load_recording`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Final

import numpy as np

from crowdnav_mesrnn.data.constants import ETH_UCY_DT_S, FRAME_STEP
from crowdnav_mesrnn.data.recordings import Recording

SYNTHETIC_NAME: Final[str] = "synthetic"
EMPTY_NAME: Final[str] = "empty"


def make_recording(
    name: str,
    positions: np.ndarray,
    present: np.ndarray,
    step_s: float = ETH_UCY_DT_S,
    ped_ids: np.ndarray | None = None,
) -> Recording:
    """A :class:`Recording` from dense arrays.

    Args:
        name: recording name (cache key of forecasts: give different crowds different names).
        positions: ``(F, P, 2)`` metres at consecutive annotations ``step_s`` apart.
        present: ``(F, P)`` bool.
        step_s: seconds per annotation.
        ped_ids: ``(P,)`` ids (default ``1..P``).
    """
    positions = np.asarray(positions, dtype=np.float64)
    present = np.asarray(present, dtype=bool)
    if positions.ndim != 3 or positions.shape[-1] != 2 or present.shape != positions.shape[:2]:
        raise ValueError(f"positions must be (F, P, 2) and present (F, P), got {positions.shape} and {present.shape}")
    if not np.all(np.isfinite(positions[present])):
        raise ValueError("positions hold NaN or infinite values where present")
    num_frames, num_peds = present.shape
    frames = np.arange(num_frames, dtype=np.int64) * FRAME_STEP
    ids = np.arange(1, num_peds + 1, dtype=np.int64) if ped_ids is None else np.asarray(ped_ids, dtype=np.int64)
    return Recording(
        name, Path(f"<{name}>"), float(step_s), frames, ids, np.where(present[..., None], positions, 0.0), present
    )


def scripted_recording(
    trajectories: Sequence[np.ndarray],
    start_steps: Sequence[int] | None = None,
    num_steps: int | None = None,
    step_s: float = ETH_UCY_DT_S,
    name: str = "scripted",
) -> Recording:
    """A crowd of scripted pedestrians, for tests and examples.

    Args:
        trajectories: one ``(T_i, 2)`` array per pedestrian, metres, at consecutive annotations.
        start_steps: annotation index of each trajectory's first row (default 0).
        num_steps: number of annotations of the recording (default: until the last trajectory ends).
        step_s: seconds per annotation.
        name: recording name.
    """
    starts = [0] * len(trajectories) if start_steps is None else list(start_steps)
    if len(starts) != len(trajectories):
        raise ValueError(f"{len(trajectories)} trajectories but {len(starts)} start steps")
    trajs = [np.asarray(t, dtype=np.float64).reshape(-1, 2) for t in trajectories]
    end = max((s + len(t) for s, t in zip(starts, trajs, strict=True)), default=1)
    num = end if num_steps is None else num_steps
    positions = np.zeros((num, len(trajs), 2))
    present = np.zeros((num, len(trajs)), dtype=bool)
    for j, (s, t) in enumerate(zip(starts, trajs, strict=True)):
        stop = min(s + len(t), num)
        positions[s:stop, j] = t[: stop - s]
        present[s:stop, j] = True
    return make_recording(name, positions, present, step_s)


def empty_recording(duration_s: float = 3600.0, step_s: float = ETH_UCY_DT_S) -> Recording:
    """A recording without pedestrians (frames only), for navigation in an empty scene."""
    num = math.ceil(duration_s / step_s) + 1
    return make_recording(EMPTY_NAME, np.zeros((num, 0, 2)), np.zeros((num, 0), dtype=bool), step_s)


@lru_cache(maxsize=8)
def synthetic_recording(
    seed: int = 0,
    duration_s: float = 300.0,
    arrival_rate_per_s: float = 0.8,
    area_m: tuple[float, float] = (16.0, 12.0),
    step_s: float = ETH_UCY_DT_S,
) -> Recording:
    """A social-force crowd crossing a rectangular scene, recorded like ETH/UCY (every ``step_s``).

    Pedestrians enter at a random edge (70 % left/right, 30 % top/bottom), walk to a random point of
    the opposite edge at a preferred speed ~ N(1.2, 0.2) m/s (clipped to 0.6-1.8), and repel each
    other with an anisotropic exponential force (Helbing-Molnar form: A = 2 m/s², B = 0.3 m,
    radius 0.3 m, relaxation 0.5 s, lambda 0.35). Integrated with 0.1 s semi-implicit Euler steps
    after a 30 s warm-up. Deterministic in its arguments (cached).

    Returns:
        a :class:`Recording` named ``"synthetic"`` with ``area_m`` as its extent (metres, origin at
        the lower-left corner).
    """
    rng = np.random.default_rng(seed)
    width, height = float(area_m[0]), float(area_m[1])
    h = 0.1
    per_record = max(1, round(step_s / h))
    h = step_s / per_record
    tau, a_rep, b_rep, radius, lam = 0.5, 2.0, 0.3, 0.3, 0.35
    warmup = round(30.0 / h)
    total = warmup + round(duration_s / h)
    pos = np.zeros((0, 2))
    vel = np.zeros((0, 2))
    goal = np.zeros((0, 2))
    v0 = np.zeros(0)
    pid = np.zeros(0, dtype=np.int64)
    next_id = 0
    frames_pos: list[np.ndarray] = []
    frames_id: list[np.ndarray] = []

    def edge_point(side: int) -> np.ndarray:
        if side in (0, 1):  # left, right
            return np.array([0.0 if side == 0 else width, rng.uniform(1.0, height - 1.0)])
        return np.array([rng.uniform(1.0, width - 1.0), 0.0 if side == 2 else height])

    for step in range(total):
        if rng.random() < arrival_rate_per_s * h:
            side = int(rng.integers(0, 2)) if rng.random() < 0.7 else int(rng.integers(2, 4))
            entry = edge_point(side)
            if len(pos) == 0 or np.min(np.linalg.norm(pos - entry, axis=1)) > 1.0:
                target = edge_point(side ^ 1)
                speed = float(np.clip(rng.normal(1.2, 0.2), 0.6, 1.8))
                direction = (target - entry) / np.linalg.norm(target - entry)
                pos = np.vstack([pos, entry])
                vel = np.vstack([vel, direction * speed])
                goal = np.vstack([goal, target])
                v0 = np.append(v0, speed)
                pid = np.append(pid, next_id)
                next_id += 1
        if len(pos):
            to_goal = goal - pos
            dist_goal = np.linalg.norm(to_goal, axis=1, keepdims=True)
            e = to_goal / np.maximum(dist_goal, 1e-9)
            force = (v0[:, None] * e - vel) / tau
            if len(pos) > 1:
                diff = pos[:, None, :] - pos[None, :, :]
                d = np.linalg.norm(diff, axis=-1)
                np.fill_diagonal(d, np.inf)
                n_ij = diff / np.maximum(d, 1e-9)[..., None]
                cos_phi = -np.einsum("ijk,ik->ij", n_ij, e)
                weight = lam + (1 - lam) * (1 + cos_phi) / 2
                mag = a_rep * np.exp((2 * radius - d) / b_rep) * weight
                force += np.einsum("ij,ijk->ik", mag, n_ij)
            vel = vel + force * h
            speed = np.linalg.norm(vel, axis=1, keepdims=True)
            vel = vel * np.minimum(1.0, 1.3 * v0[:, None] / np.maximum(speed, 1e-9))
            pos = pos + vel * h
            keep = (np.linalg.norm(goal - pos, axis=1) > 0.5) & np.all(
                (pos > -1.0) & (pos < np.array([width, height]) + 1.0), axis=1
            )
            pos, vel, goal, v0, pid = pos[keep], vel[keep], goal[keep], v0[keep], pid[keep]
        if step >= warmup and (step - warmup) % per_record == 0:
            frames_pos.append(pos.copy())
            frames_id.append(pid.copy())
    ids = np.unique(np.concatenate(frames_id)) if frames_id else np.zeros(0, dtype=np.int64)
    col = {int(i): c for c, i in enumerate(ids)}
    positions = np.zeros((len(frames_pos), len(ids), 2))
    present = np.zeros((len(frames_pos), len(ids)), dtype=bool)
    for f, (p, i) in enumerate(zip(frames_pos, frames_id, strict=True)):
        cols = np.array([col[int(x)] for x in i], dtype=np.int64)
        if len(cols):
            positions[f, cols] = p
            present[f, cols] = True
    return make_recording(SYNTHETIC_NAME, positions, present, step_s, ped_ids=ids + 1)


def overlay_recording(recording: Recording, copies: int, window_s: tuple[float, float] | None = None) -> Recording:
    """A denser crowd from one recording alone: ``copies`` time-shifted copies of it overlaid on the original.

    Within the frames whose time lies in ``window_s`` (default: the whole recording; the environment passes its
    ``episode_time`` window, so training-period pedestrians never appear in validation episodes or the reverse),
    copy ``j`` (1..copies) shows at frame ``i`` what the recording shows at frame ``i - s_j`` (cyclically within the
    window), ``s_j = round(j W / (copies + 1))`` of the window's ``W`` frames: evenly spaced shifts. The cyclic wrap
    cuts a copy's tracks there (the part before and the part after the wrap are different pedestrians), so nobody
    jumps across the scene. Outside the window only the original pedestrians are present. Copies' pedestrians get
    new ids above the recording's; like every replayed pedestrian they ignore everyone (copies pass through each
    other and through the originals, which real crowds would not).

    Args:
        recording: the recording (positions, presence, frames and ``step_s`` kept; the name is kept too, so the
            forecasts come from the same out-of-sample predictor).
        copies: how many copies (0 returns ``recording`` itself).
        window_s: ``(earliest, latest)`` seconds since the first frame; frames with ``earliest <= t < latest``
            (the last frame too when ``latest`` is the recording's end) are overlaid.

    Returns:
        a recording with the same frames and ``(F, P', 2)`` pedestrians, ``P' >= P``.
    """
    if copies < 0:
        raise ValueError(f"copies must be >= 0, got {copies!r}")
    if copies == 0:
        return recording
    times = recording.times_s()
    lo, hi = (0.0, float(times[-1])) if window_s is None else window_s
    inside = (times >= lo - 1e-9) & ((times < hi - 1e-9) | (np.isclose(hi, times[-1]) & (times <= hi + 1e-9)))
    idx = np.flatnonzero(inside)
    if len(idx) < copies + 1:
        raise ValueError(
            f"overlaying {copies} copies of {recording.name!r} needs at least {copies + 1} frames in the window "
            f"{lo:.1f}..{hi:.1f} s, got {len(idx)}"
        )
    i0, width = int(idx[0]), len(idx)  # the window's frames are consecutive (times increase with the index)
    num_frames = len(times)
    blocks_pos, blocks_present = [recording.positions], [recording.present]
    for j in range(1, copies + 1):
        shift = round(j * width / (copies + 1))
        # (source frames, target frames) of the part that does not wrap and of the part that does
        for src, dst in ((slice(i0, i0 + width - shift), slice(i0 + shift, i0 + width)),
                         (slice(i0 + width - shift, i0 + width), slice(i0, i0 + shift))):  # fmt: skip
            present = np.zeros((num_frames, recording.present.shape[1]), dtype=bool)
            present[dst] = recording.present[src]
            cols = np.flatnonzero(present.any(axis=0))
            positions = np.zeros((num_frames, len(cols), 2))
            positions[dst] = recording.positions[src][:, cols]
            blocks_pos.append(positions)
            blocks_present.append(present[:, cols])
    added = sum(p.shape[1] for p in blocks_present[1:])
    first_id = int(recording.ped_ids.max(initial=0)) + 1
    return Recording(
        recording.name,
        recording.path,
        recording.step_s,
        recording.frames,
        np.concatenate([recording.ped_ids, first_id + np.arange(added, dtype=np.int64)]),
        np.concatenate(blocks_pos, axis=1),
        np.concatenate(blocks_present, axis=1),
    )
