"""The replay: a time slice of a recording in continuous time (what the world is), and what the robot's
tracker perceives of it (the latest annotation at or before a time). Replayed pedestrians ignore the robot.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Final

import numpy as np

from crowdnav_mesrnn.data.recordings import Recording

#: Two times closer than this (seconds) are the same instant (env times are t0 + n * dt_s in floating point).
TIME_TOL_S: Final[float] = 1e-6


@dataclass(frozen=True)
class ReplayState:
    """Pedestrian states at ``T`` times.

    Attributes:
        positions: ``(T, N, 2)`` metres, world frame (meaningless where not present).
        velocities: ``(T, N, 2)`` m/s (the slope of the linear interpolation; at an annotation time
            the slope of the following interval, else of the preceding one, else 0).
        present: ``(T, N)`` bool: the pedestrian is in the replay at that time.
    """

    positions: np.ndarray
    velocities: np.ndarray
    present: np.ndarray


@dataclass(frozen=True)
class Perception:
    """What the robot's tracker reports at one time: the latest annotation at or before it.

    Attributes:
        index: the annotation's index in the replay (-1 before the replay's first annotation).
        time_s: the annotation's time, seconds.
        age_s: time since that annotation, seconds (0 at an annotation time).
        positions: ``(N, 2)`` metres at the annotation (meaningless where not present; a read-only view).
        velocities: ``(N, 2)`` m/s: the slope of the interval ending at the annotation, 0 for a pedestrian
            that was not at the previous annotation (a read-only view).
        present: ``(N,)`` bool: annotated there, and the annotation is younger than one annotation step
            (a track not updated for a whole step is dropped, so nobody lingers through an annotation gap).
    """

    index: int
    time_s: float
    age_s: float
    positions: np.ndarray
    velocities: np.ndarray
    present: np.ndarray


class Replay:
    """Continuous-time replay of a time slice of a recording.

    Positions are interpolated linearly in time between consecutive annotations (``recording.step_s``
    apart, larger gaps are real time). A pedestrian is in the replay at an annotation time if the
    file has its row there, and strictly between two annotations if it has rows at both. So at every
    annotation time the replayed positions equal the file's, bit for bit.

    Args:
        recording: the recording.
        t_from_s: first time needed, seconds since the recording's first frame (default: start).
        t_to_s: last time needed (default: end). Only pedestrians present in the slice are kept.

    Attributes:
        name: the recording's name.
        step_s: seconds per annotation.
        times: ``(F,)`` seconds of the sliced annotations.
        columns: ``(N,)`` column of each replayed pedestrian in ``recording.positions``.
        ped_ids: ``(N,)`` pedestrian ids.
    """

    def __init__(self, recording: Recording, t_from_s: float | None = None, t_to_s: float | None = None) -> None:
        times = recording.times_s()
        num = len(times)
        lo = 0 if t_from_s is None else max(int(np.searchsorted(times, t_from_s + TIME_TOL_S, "right")) - 2, 0)
        hi = num if t_to_s is None else min(int(np.searchsorted(times, t_to_s - TIME_TOL_S, "left")) + 2, num)
        present = recording.present[lo:hi]
        cols = np.flatnonzero(present.any(axis=0))
        self.recording = recording
        self.name = recording.name
        self.step_s = float(recording.step_s)
        self.times = np.ascontiguousarray(times[lo:hi], dtype=np.float64)
        self.columns = cols
        self.ped_ids = recording.ped_ids[cols]
        self.present = np.ascontiguousarray(present[:, cols])
        self.positions = np.ascontiguousarray(recording.positions[lo:hi][:, cols], dtype=np.float64)
        f, n = self.present.shape
        valid = np.zeros((f, n), dtype=bool)
        vel = np.zeros((f, n, 2))
        if f > 1:
            valid[:-1] = self.present[:-1] & self.present[1:]
            slope = np.diff(self.positions, axis=0) / np.diff(self.times)[:, None, None]
            vel[:-1] = np.where(valid[:-1, :, None], slope, 0.0)
        self.valid = valid
        self.slopes = vel
        prev_valid = np.zeros_like(valid)
        prev_vel = np.zeros_like(vel)
        prev_valid[1:] = valid[:-1]
        prev_vel[1:] = vel[:-1]
        self.annotation_velocity = np.where(valid[..., None], vel, np.where(prev_valid[..., None], prev_vel, 0.0))
        # slope of the interval ending at each annotation (0 where the pedestrian was not at the previous one)
        self.arrival_velocity = np.where(prev_valid[..., None], prev_vel, 0.0)
        # presence at an annotation (index 0) and strictly after it (index 1): (F, 2, N)
        self._presence = np.ascontiguousarray(np.stack([self.present, self.valid], axis=1))
        for arr in (self.positions, self.present, self.arrival_velocity):
            arr.setflags(write=False)  # perception hands out views
        self._times_list = self.times.tolist()
        self._t_lo = float(self.times[0]) - TIME_TOL_S
        self._t_hi = float(self.times[-1]) + TIME_TOL_S

    @property
    def num_pedestrians(self) -> int:
        return int(self.present.shape[1])

    @property
    def t_start_s(self) -> float:
        return float(self.times[0])

    @property
    def t_end_s(self) -> float:
        return float(self.times[-1])

    def positions_at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(T, N, 2)`` metres and presence ``(T, N)`` at ``times_s`` ``(T,)`` seconds (the hot path).

        Positions are meaningless where the pedestrian is not present.
        """
        ts = np.asarray(times_s, dtype=np.float64)
        idx = np.searchsorted(self.times, ts + TIME_TOL_S, "right") - 1
        np.maximum(idx, 0, out=idx)
        tau = ts - self.times[idx]
        inner = tau > TIME_TOL_S  # strictly between two annotations; else at one (or before the slice)
        tau *= inner
        pos = self.positions[idx] + self.slopes[idx] * tau[:, None, None]
        present = self._presence[idx, inner.astype(np.intp)]
        if ts.min() < self._t_lo or ts.max() > self._t_hi:
            present[(ts < self._t_lo) | (ts > self._t_hi)] = False
        return pos, present

    def rows_at(self, times_s: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(m, T, 2)`` metres and presence ``(m, T)`` of row ``rows[i]`` at ``times_s[i]`` (``times_s``
        ``(m, T)`` seconds, ``rows`` ``(m,)``): :meth:`positions_at` of those rows only (the same arithmetic element by
        element)."""
        ts = np.asarray(times_s, dtype=np.float64)
        idx = np.searchsorted(self.times, ts + TIME_TOL_S, "right") - 1
        np.maximum(idx, 0, out=idx)
        tau = ts - self.times[idx]
        inner = tau > TIME_TOL_S
        tau *= inner
        r = np.asarray(rows)[:, None]
        pos = self.positions[idx, r] + self.slopes[idx, r] * tau[..., None]
        present = self._presence[idx, inner.astype(np.intp), r]
        present[(ts < self._t_lo) | (ts > self._t_hi)] = False
        return pos, present

    def velocity_at(self, t_s: float) -> np.ndarray:
        """``(N, 2)`` velocities at one time, m/s (0 where not present)."""
        i = max(bisect.bisect_right(self._times_list, t_s + TIME_TOL_S) - 1, 0)
        if t_s - self._times_list[i] > TIME_TOL_S:
            return self.slopes[i].copy()
        return self.annotation_velocity[i].copy()

    def perceived_at(self, t_s: float) -> Perception:
        """The tracker's report at ``t_s``: positions, velocities and presence of the latest annotation at or before
        ``t_s`` (causal: nothing annotated after ``t_s`` enters it; see :class:`Perception`)."""
        i = bisect.bisect_right(self._times_list, t_s + TIME_TOL_S) - 1
        n = self.num_pedestrians
        if i < 0:
            return Perception(-1, t_s, 0.0, np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n, dtype=bool))
        tau = self._times_list[i]
        age = t_s - tau if t_s - tau > TIME_TOL_S else 0.0
        present = self.present[i] if age < self.step_s - TIME_TOL_S else np.zeros(n, dtype=bool)
        return Perception(i, tau, age, self.positions[i], self.arrival_velocity[i], present)

    def state_at(self, times_s: np.ndarray | float) -> ReplayState:
        """Positions, velocities and presence at ``times_s`` (``(T,)`` or scalar seconds -> ``T = 1``)."""
        ts = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        pos, present = self.positions_at(ts)
        vel = np.stack([self.velocity_at(float(t)) for t in ts]) if len(ts) else np.zeros((0, self.num_pedestrians, 2))
        return ReplayState(pos, np.where(present[..., None], vel, 0.0), present)
