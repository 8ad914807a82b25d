"""Episodes: where and when the robot starts, its goal and time limit, drawn from recordings with the
environment's random generator, and the policy-independent crowd density of an episode.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from crowdnav_mesrnn.data.recordings import Recording
from envs.replay import TIME_TOL_S


@dataclass(frozen=True)
class Episode:
    """One episode's setting.

    Attributes:
        recording: the crowd.
        t0_s: start time, seconds since the recording's first frame.
        start: ``(2,)`` robot start, metres.
        goal: ``(2,)`` robot goal, metres.
        time_limit_s: truncation after this many seconds.
        max_steps: truncation after this many control steps.
        crowd_density: mean number of pedestrians within the sensor range of the straight start-goal segment,
            over the annotation times of ``[t0_s, t0_s + time_limit_s]`` (every ``step_s``; frames the file does
            not list count as empty; policy-independent).
        pedestrians_near_path: distinct pedestrians within the sensor range of that segment at those times.
    """

    recording: Recording
    t0_s: float
    start: np.ndarray
    goal: np.ndarray
    time_limit_s: float
    max_steps: int
    crowd_density: float = 0.0
    pedestrians_near_path: int = 0


def crowd_near_path(
    recording: Recording, t0_s: float, time_limit_s: float, start: np.ndarray, goal: np.ndarray, range_m: float
) -> tuple[float, int]:
    """``(mean count, distinct pedestrians)`` within ``range_m`` (centre distance) of the segment ``start``-``goal``
    at the recording's annotation times in ``[t0_s, t0_s + time_limit_s]`` (0, 0 when there are none).

    The mean is over every annotation time of the window (every ``step_s``), not only over the frames the
    file lists: ETH/UCY files have no rows for a frame without pedestrians, so a gap in the frame numbers (or
    time after the recording's end) is time when nobody was there, and counts as zero.
    """
    times = recording.times_s()
    i0 = int(np.searchsorted(times, t0_s - TIME_TOL_S, "left"))
    i1 = int(np.searchsorted(times, t0_s + time_limit_s + TIME_TOL_S, "right"))
    if i1 <= i0:
        return 0.0, 0
    step = float(recording.step_s)
    first = math.ceil((t0_s - TIME_TOL_S) / step)
    last = math.floor((t0_s + time_limit_s + TIME_TOL_S) / step)
    slots = max(last - first + 1, i1 - i0)
    present = recording.present[i0:i1]
    seg = np.asarray(goal, dtype=np.float64) - np.asarray(start, dtype=np.float64)
    length2 = float(seg @ seg)
    rel = recording.positions[i0:i1] - np.asarray(start, dtype=np.float64)
    along = (rel @ seg) / length2 if length2 > 0 else np.zeros(present.shape)
    # the distances of the annotated positions only (element by element, so as over the whole window)
    frame, col = np.nonzero(present)
    along = np.clip(along[frame, col], 0.0, 1.0)
    dist = np.linalg.norm(rel[frame, col] - along[:, None] * seg, axis=-1)
    near = dist <= range_m
    return float(near.sum()) / slots, len(np.unique(col[near]))


def _annotated_cells(present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(cells, first)``: the flat indices of ``present`` ``(F, P)``'s True cells in row-major order, and ``(F + 1,)``
    where each frame's cells start among them (``first[F]``: their number)."""
    first = np.zeros(len(present) + 1, dtype=np.int64)
    np.cumsum(present.sum(axis=1), out=first[1:])
    return np.flatnonzero(present), first


def recording_extent(recording: Recording, margin_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` corners of the box holding every annotated position (plus a margin), metres.

    A recording without pedestrians gets a 16 m x 12 m box at the origin.
    """
    if not recording.present.any():
        return np.array([0.0, 0.0]), np.array([16.0, 12.0])
    p = recording.positions[recording.present]
    return p.min(axis=0) - margin_m, p.max(axis=0) + margin_m


def episode_time_window(rec: Recording, episode_time: str, val_fraction: float) -> tuple[float, float]:
    """``(earliest, latest)`` seconds (since the recording's first frame) an episode of ``rec`` may cover under
    ``episode_time`` (``all``, ``train``: before the last ``val_fraction`` of the duration, ``val``: inside it)."""
    end = float(rec.times_s()[-1])
    cut = (1.0 - val_fraction) * end
    if episode_time == "train":
        return 0.0, cut
    if episode_time == "val":
        return cut, end
    return 0.0, end


class EpisodeSampler:
    """Draws episodes from recordings with the environment's random generator.

    Start times lie on a grid of ``dt_s`` from each recording's first frame (so forecast caches are
    shared between episodes) and leave room for the observed history and the whole episode. The
    start and goal are ``start_goal_distance_m`` apart, inside the box of the recording's
    pedestrian positions, on a straight line through a position a pedestrian occupies during the
    episode; nobody is within ``start_clearance_m`` (gap) of the start at t0.
    """

    MAX_TRIES: Final[int] = 500
    #: Episodes drawn at most to find one with a pedestrian near its path (``require_pedestrians``).
    MAX_DRAWS: Final[int] = 200

    def __init__(
        self,
        recordings: Sequence[Recording],
        dt_s: float,
        history_steps: int,
        distance_m: tuple[float, float],
        clearance_gap_m: float,
        robot_radius_m: float,
        ped_radius_m: float,
        speed_mps: float,
        time_limit_factor: float,
        sensor_range_m: float = 6.0,
        require_pedestrians: bool = False,
        episode_time: str = "all",
        val_fraction: float = 0.2,
    ) -> None:
        self.recordings = list(recordings)
        self.sensor_range_m = sensor_range_m
        self.require_pedestrians = require_pedestrians
        self.episode_time = episode_time
        self.val_fraction = val_fraction
        self.dt_s = dt_s
        self.history_steps = history_steps
        self.distance_m = distance_m
        self.clear_m = clearance_gap_m + robot_radius_m + ped_radius_m
        self.speed_mps = speed_mps
        self.time_limit_factor = time_limit_factor
        self.extents = {r.name: recording_extent(r) for r in self.recordings}
        # every annotated (frame, column) of each recording in row-major order, and where each frame's start in it
        self._annotated = {r.name: _annotated_cells(r.present) for r in self.recordings}
        durations = np.array([r.times_s()[-1] for r in self.recordings], dtype=np.float64)
        self.weights = np.maximum(durations, 1e-9) / np.maximum(durations, 1e-9).sum()

    def time_limit(self, start: np.ndarray, goal: np.ndarray) -> tuple[float, int]:
        dist = float(np.linalg.norm(goal - start))
        limit = self.time_limit_factor * max(dist, 1e-6) / self.speed_mps
        steps = max(1, math.ceil(limit / self.dt_s - 1e-9))
        return steps * self.dt_s, steps

    def recording_named(self, name: str) -> Recording:
        for r in self.recordings:
            if r.name == name:
                return r
        raise ValueError(
            f"unknown recording {name!r} for this env; valid: {', '.join(r.name for r in self.recordings)}"
        )

    def time_window(self, rec: Recording) -> tuple[float, float]:
        """``(earliest, latest)`` seconds an episode of ``rec`` may cover under ``episode_time``."""
        return episode_time_window(rec, self.episode_time, self.val_fraction)

    def sample(
        self,
        rng: np.random.Generator,
        recording: str | None = None,
        t0_s: float | None = None,
        start: np.ndarray | None = None,
        goal: np.ndarray | None = None,
        time_limit_s: float | None = None,
    ) -> Episode:
        """An episode; any of recording, start time, start, goal and time limit may be fixed.

        With ``require_pedestrians`` episodes are drawn until one has a pedestrian near its path (all draws
        come from ``rng``, so the result is a function of the generator's state); an episode fixed entirely
        by the arguments is returned as it is.
        """
        fixed = t0_s is not None and start is not None and goal is not None
        for _ in range(self.MAX_DRAWS):
            ep = self._draw(rng, recording, t0_s, start, goal, time_limit_s)
            if not self.require_pedestrians or fixed or ep.pedestrians_near_path > 0:
                return ep
        raise RuntimeError(
            f"require_pedestrians: no episode out of {self.MAX_DRAWS} drawn had a pedestrian within "
            f"{self.sensor_range_m} m of its path; the recording(s) {', '.join(r.name for r in self.recordings)} "
            "hold too few pedestrians for the fixed options (or set require_pedestrians=False)"
        )

    def _draw(
        self,
        rng: np.random.Generator,
        recording: str | None,
        t0_s: float | None,
        start: np.ndarray | None,
        goal: np.ndarray | None,
        time_limit_s: float | None,
    ) -> Episode:
        if recording is not None:
            rec = self.recording_named(recording)
        else:
            rec = self.recordings[int(rng.choice(len(self.recordings), p=self.weights))]
        times = rec.times_s()
        lo, hi = self.extents[rec.name]
        for key, point in (("start", start), ("goal", goal)):
            if (
                point is not None
                and (start is None or goal is None)
                and not (np.all(point >= lo) and np.all(point <= hi))
            ):
                raise ValueError(
                    f"reset option {key!r} {np.asarray(point).tolist()} lies outside the scene of {rec.name!r} (x in "
                    f"[{lo[0]:.1f}, {hi[0]:.1f}], y in [{lo[1]:.1f}, {hi[1]:.1f}] m, where its pedestrians walk), where "
                    "the other end is placed; give both 'start' and 'goal' to place the robot anywhere"
                )
        if t0_s is not None and not 0.0 <= t0_s < float(times[-1]):
            raise ValueError(
                f"reset option 't0_s' = {t0_s!r} lies outside the recording {rec.name!r}: valid [0, {times[-1]:.2f}) s"
            )
        if t0_s is not None and self.episode_time != "all":
            window_lo, window_hi = self.time_window(rec)
            if not window_lo - TIME_TOL_S <= t0_s < window_hi:
                raise ValueError(
                    f"reset option 't0_s' = {t0_s!r} lies outside the {self.episode_time!r} episode time of "
                    f"{rec.name!r}: [{window_lo:.2f}, {window_hi:.2f}) s"
                )
        for _ in range(self.MAX_TRIES):
            dist = float(rng.uniform(*self.distance_m))
            if start is not None and goal is not None:
                dist = float(np.linalg.norm(np.asarray(goal) - np.asarray(start)))
            limit_s, steps = self.time_limit(np.zeros(2), np.array([dist, 0.0]))
            if time_limit_s is not None:
                steps = max(1, math.ceil(time_limit_s / self.dt_s - 1e-9))
                limit_s = steps * self.dt_s
            if t0_s is None:
                window_lo, window_hi = self.time_window(rec)
                history_s = self.history_steps * rec.step_s
                first = math.ceil(min(max(history_s, window_lo), window_hi) / self.dt_s - 1e-9)
                last = math.floor((window_hi - limit_s) / self.dt_s + 1e-9)
                if last < first:
                    if self.episode_time != "all":
                        continue  # another distance (a shorter time limit) may fit
                    first, last = 0, max(0, math.floor((times[-1] - limit_s) / self.dt_s + 1e-9))
                t0 = float(rng.integers(first, last + 1)) * self.dt_s
            else:
                t0 = float(t0_s)
            if start is not None and goal is not None:
                s, g = np.asarray(start, dtype=np.float64), np.asarray(goal, dtype=np.float64)
                return self._episode(rec, t0, s.copy(), g.copy(), limit_s, steps)
            cross = self._crossing_point(rec, times, t0, limit_s, rng, lo, hi)
            theta = float(rng.uniform(0.0, 2.0 * math.pi))
            u = np.array([math.cos(theta), math.sin(theta)])
            frac = float(rng.uniform(0.25, 0.75))
            s = cross - frac * dist * u if start is None else np.asarray(start, dtype=np.float64)
            g = s + dist * u if goal is None else np.asarray(goal, dtype=np.float64)
            if start is None and goal is not None:
                s = g - dist * u
            if not (np.all(s >= lo) and np.all(s <= hi) and np.all(g >= lo) and np.all(g <= hi)):
                continue
            if not self._clear(rec, times, t0, s):
                continue
            if time_limit_s is None:
                limit_s, steps = self.time_limit(s, g)
            return self._episode(rec, t0, s, g, limit_s, steps)
        raise RuntimeError(
            f"could not place a start and goal {self.distance_m} m apart in {rec.name!r} after {self.MAX_TRIES} tries "
            f"(extent {lo.round(1).tolist()}..{hi.round(1).tolist()} m, episode_time {self.episode_time!r}); lower "
            "start_goal_distance_m or start_clearance_m"
        )

    def _episode(self, rec: Recording, t0: float, s: np.ndarray, g: np.ndarray, limit_s: float, steps: int) -> Episode:
        density, near = crowd_near_path(rec, t0, limit_s, s, g, self.sensor_range_m)
        return Episode(rec, t0, s, g, limit_s, steps, density, near)

    def _crossing_point(
        self,
        rec: Recording,
        times: np.ndarray,
        t0: float,
        limit_s: float,
        rng: np.random.Generator,
        lo: np.ndarray,
        hi: np.ndarray,
    ) -> np.ndarray:
        i0 = int(np.searchsorted(times, t0 - TIME_TOL_S, "left"))
        i1 = int(np.searchsorted(times, t0 + limit_s + TIME_TOL_S, "right"))
        cells, first = self._annotated[rec.name]  # the window's cells: np.nonzero(rec.present[i0:i1]), in order
        count = max(int(first[i1] - first[i0]), 0)
        if count == 0:
            return rng.uniform(lo, hi)
        k = int(rng.integers(count))
        frame, col = divmod(int(cells[first[i0] + k]), rec.present.shape[1])
        return rec.positions[frame, col].astype(np.float64)

    def _clear(self, rec: Recording, times: np.ndarray, t0: float, start: np.ndarray) -> bool:
        """Nobody within the clearance of ``start`` at the annotations around ``t0`` nor, between them, at ``t0``
        itself (on the line between two annotations a pedestrian can come closer than at either end)."""
        i = int(np.searchsorted(times, t0 + TIME_TOL_S, "right")) - 1
        if i < 0:
            return True
        rows = slice(i, min(i + 2, len(times)))
        mask = rec.present[rows]
        if mask.any():
            d = np.linalg.norm(rec.positions[rows][mask] - start, axis=-1)
            if not np.all(d >= self.clear_m):
                return False
        tau = t0 - float(times[i])
        if tau > TIME_TOL_S and i + 1 < len(times):
            both = rec.present[i] & rec.present[i + 1]
            p0, p1 = rec.positions[i, both], rec.positions[i + 1, both]
            p = p0 + (p1 - p0) / (times[i + 1] - times[i]) * tau  # as Replay.positions_at
            if len(p) and not np.all(np.linalg.norm(p - start, axis=-1) >= self.clear_m):
                return False
        return True
