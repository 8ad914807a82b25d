"""The replays of W worlds side by side: each world's :class:`envs.replay.Replay` copied into padded arrays, so that
positions at any times and what each robot's tracker perceives are looked up for every world in one numpy pass.

Results equal each world's own :meth:`~envs.replay.Replay.positions_at` and :meth:`~envs.replay.Replay.perceived_at`
bit for bit: the same index search (on the recording's time array, which the replay slices), the same arithmetic
element by element; padded rows are never present.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from envs.replay import TIME_TOL_S, Replay

_GROW: Final[float] = 1.5


class BatchedReplay:
    """Padded copies of W replays.

    Attributes:
        replays: the worlds' :class:`~envs.replay.Replay` (None before a world's first episode).
        width: P, the padded number of rows (>= every world's pedestrians; only grows).
        num_rows: ``(W,)`` pedestrians of each world's replay.
        columns: ``(W, P)`` recording column of each world's rows (:attr:`envs.replay.Replay.columns`).
    """

    def __init__(self, num_worlds: int) -> None:
        self.num_worlds = num_worlds
        self.replays: list[Replay | None] = [None] * num_worlds
        self.width = 1
        self._frames = 1
        self._alloc(self._frames, self.width)
        self.num_rows = np.zeros(num_worlds, dtype=np.int64)
        self._num_frames = np.ones(num_worlds, dtype=np.int64)
        self._first = np.zeros(num_worlds, dtype=np.int64)  # index of the replay's first frame in the recording's
        self._step_s = np.ones(num_worlds)
        self._t_lo = np.zeros(num_worlds)
        self._t_hi = np.zeros(num_worlds)
        self._rec_times: dict[int, np.ndarray] = {}  # id(recording) -> its times_s()
        self._rec_of = np.zeros(num_worlds, dtype=np.int64)

    def _alloc(self, frames: int, width: int) -> None:
        w = self.num_worlds
        self.times = np.zeros((w, frames))
        self.positions = np.zeros((w, frames, width, 2))
        self.slopes = np.zeros((w, frames, width, 2))
        self.presence = np.zeros((w, frames, 2, width), dtype=bool)
        self.present = np.zeros((w, frames, width), dtype=bool)
        self.arrival_velocity = np.zeros((w, frames, width, 2))
        self.columns = np.zeros((w, width), dtype=np.int64)

    def _grow(self, frames: int, width: int) -> None:
        old = (
            self.times,
            self.positions,
            self.slopes,
            self.presence,
            self.present,
            self.arrival_velocity,
            self.columns,
        )
        f0, p0 = self._frames, self.width
        self._frames, self.width = frames, width
        self._alloc(frames, width)
        self.times[:, :f0] = old[0]
        self.positions[:, :f0, :p0] = old[1]
        self.slopes[:, :f0, :p0] = old[2]
        self.presence[:, :f0, :, :p0] = old[3]
        self.present[:, :f0, :p0] = old[4]
        self.arrival_velocity[:, :f0, :p0] = old[5]
        self.columns[:, :p0] = old[6]

    def set_world(self, w: int, replay: Replay) -> None:
        """World ``w`` now replays ``replay``."""
        f, n = replay.present.shape
        if f > self._frames or n > self.width:
            self._grow(max(f, int(self._frames * _GROW)), max(n, int(self.width * _GROW)))
        self.replays[w] = replay
        rec = replay.recording
        rec_times = self._rec_times.get(id(rec))
        if rec_times is None:
            rec_times = self._rec_times[id(rec)] = np.asarray(rec.times_s(), dtype=np.float64)
        self._rec_of[w] = id(rec)
        self._first[w] = int(np.searchsorted(rec_times, replay.times[0]))
        self.num_rows[w] = n
        self._num_frames[w] = f
        self._step_s[w] = replay.step_s
        self._t_lo[w] = float(replay.times[0]) - TIME_TOL_S
        self._t_hi[w] = float(replay.times[-1]) + TIME_TOL_S
        # rows past n and frames past f are never present (frames past f are never read: indices are clamped);
        # their positions and velocities are left as they were (finite, never used)
        self.times[w, :f] = replay.times
        self.positions[w, :f, :n] = replay.positions
        self.slopes[w, :f, :n] = replay.slopes
        self.presence[w, :f, :, :n] = replay._presence
        self.presence[w, :f, :, n:] = False
        self.present[w, :f, :n] = replay.present
        self.present[w, :f, n:] = False
        self.arrival_velocity[w, :f, :n] = replay.arrival_velocity
        self.columns[w] = 0
        self.columns[w, :n] = replay.columns

    def frame_index(self, worlds: np.ndarray, times_s: np.ndarray) -> np.ndarray:
        """``(n, T)`` index of the latest frame at or before each time (``times_s`` ``(n, T)``) in each world's replay,
        as ``searchsorted(replay.times, t + TIME_TOL_S, "right") - 1`` (-1 before the first, never past the last)."""
        out = np.empty(times_s.shape, dtype=np.int64)
        query = times_s + TIME_TOL_S
        recs = self._rec_of[worlds]
        if len(self._rec_times) == 1:  # one recording (a held-out scene): one search
            out[:] = np.searchsorted(next(iter(self._rec_times.values())), query, "right") - 1
        else:
            for rec in np.unique(recs).tolist():
                sel = recs == rec
                out[sel] = np.searchsorted(self._rec_times[rec], query[sel], "right") - 1
        out -= self._first[worlds, None]
        np.minimum(out, self._num_frames[worlds, None] - 1, out=out)
        np.maximum(out, -1, out=out)
        return out

    def positions_at(self, worlds: np.ndarray, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(n, T, P, 2)`` metres and presence ``(n, T, P)`` of worlds ``worlds`` ``(n,)`` at ``times_s``
        ``(n, T)`` seconds (:meth:`envs.replay.Replay.positions_at` of each)."""
        idx = self.frame_index(worlds, times_s)
        np.maximum(idx, 0, out=idx)
        wcol = worlds[:, None]
        shape = (*times_s.shape, self.width)
        flat = (wcol * self._frames + idx).reshape(-1)  # (world, frame) as one index: a take, not fancy indexing
        tau = times_s - self.times.reshape(-1).take(flat).reshape(times_s.shape)
        inner = tau > TIME_TOL_S
        tau *= inner
        pos = self.slopes.reshape(-1, self.width, 2).take(flat, axis=0).reshape(*shape, 2)
        pos *= tau[:, :, None, None]
        pos += self.positions.reshape(-1, self.width, 2).take(flat, axis=0).reshape(*shape, 2)
        present = self.presence.reshape(-1, self.width).take(2 * flat + inner.reshape(-1), axis=0).reshape(shape)
        outside = (times_s < self._t_lo[wcol]) | (times_s > self._t_hi[wcol])
        if outside.any():
            present[outside] = False
        return pos, present

    def rows_at(
        self, worlds: np.ndarray, times_s: np.ndarray, which: np.ndarray, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(m, T, 2)`` metres and presence ``(m, T)`` of row ``rows[i]`` of world ``worlds[which[i]]`` at
        its times ``times_s[which[i]]`` (``times_s`` ``(n, T)`` seconds, one row per world of ``worlds`` ``(n,)``;
        ``which``, ``rows`` ``(m,)``): :meth:`positions_at` of those rows only, the same arithmetic element by
        element (the frame search once per world)."""
        idx = self.frame_index(worlds, times_s)
        np.maximum(idx, 0, out=idx)
        wcol = worlds[:, None]
        frame = wcol * self._frames + idx  # (world, frame) and (world, frame, row) as one index each: takes
        tau = times_s - self.times.reshape(-1).take(frame)
        inner = tau > TIME_TOL_S
        tau *= inner
        outside = ((times_s < self._t_lo[wcol]) | (times_s > self._t_hi[wcol]))[which]
        frame, tau, inner = frame[which], tau[which], inner[which]
        cell = frame * self.width + rows[:, None]
        pos = self.slopes.reshape(-1, 2).take(cell, axis=0)
        pos *= tau[:, :, None]
        pos += self.positions.reshape(-1, 2).take(cell, axis=0)
        present = self.presence.reshape(-1).take(cell + (frame + inner) * self.width)
        if outside.any():
            present[outside] = False
        return pos, present

    def perceived_at(
        self, worlds: np.ndarray, times_s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The trackers' reports at ``times_s`` ``(n,)`` (:meth:`envs.replay.Replay.perceived_at` of each world).

        Returns:
            ``(index (n,), age_s (n,), positions (n, P, 2), velocities (n, P, 2), present (n, P))``.
        """
        i = self.frame_index(worlds, times_s[:, None])[:, 0]
        ic = np.maximum(i, 0)
        tau = self.times[worlds, ic]
        gap = times_s - tau
        age = np.where(gap > TIME_TOL_S, gap, 0.0)
        fresh = (age < self._step_s[worlds] - TIME_TOL_S) & (i >= 0)
        age = np.where(i >= 0, age, 0.0)
        present = self.present[worlds, ic] & fresh[:, None]
        pos = self.positions[worlds, ic]
        vel = self.arrival_velocity[worlds, ic]
        if (i < 0).any():
            pos[i < 0] = 0.0
            vel[i < 0] = 0.0
        return i, age, pos, vel, present
