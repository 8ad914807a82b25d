"""Crowd sources: ETH/UCY recordings replayed in continuous time, a synthetic social-force crowd,
scripted crowds for tests, and the sampling of episodes (start time, start and goal).

Every crowd is a :class:`~crowdnav_mesrnn.data.Recording` (frames x pedestrians, metres, seconds per
annotation step); :class:`Replay` turns a time slice of one into positions and velocities at any time.
Replayed pedestrians ignore the robot.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Final

import numpy as np

from crowdnav_mesrnn.data.constants import ETH_UCY_DT_S, FRAME_STEP
from crowdnav_mesrnn.data.recordings import Recording

#: Two times closer than this (seconds) are the same instant (env times are t0 + n * dt_s in floating point).
TIME_TOL_S: Final[float] = 1e-6
SYNTHETIC_NAME: Final[str] = "synthetic"
EMPTY_NAME: Final[str] = "empty"


# ----------------------------------------------------------------------------- building recordings


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


# ----------------------------------------------------------------------------- replay


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


# ----------------------------------------------------------------------------- episodes


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
            over the annotation times of ``[t0_s, t0_s + time_limit_s]`` (policy-independent).
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
    at the recording's annotation times in ``[t0_s, t0_s + time_limit_s]`` (0, 0 when there are none)."""
    times = recording.times_s()
    i0 = int(np.searchsorted(times, t0_s - TIME_TOL_S, "left"))
    i1 = int(np.searchsorted(times, t0_s + time_limit_s + TIME_TOL_S, "right"))
    if i1 <= i0:
        return 0.0, 0
    present = recording.present[i0:i1]
    seg = np.asarray(goal, dtype=np.float64) - np.asarray(start, dtype=np.float64)
    length2 = float(seg @ seg)
    rel = recording.positions[i0:i1] - np.asarray(start, dtype=np.float64)
    along = np.clip((rel @ seg) / length2, 0.0, 1.0) if length2 > 0 else np.zeros(present.shape)
    dist = np.linalg.norm(rel - along[..., None] * seg, axis=-1)
    near = present & (dist <= range_m)
    return float(near.sum(axis=1).mean()), int(near.any(axis=0).sum())


def recording_extent(recording: Recording, margin_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` corners of the box holding every annotated position (plus a margin), metres.

    A recording without pedestrians gets a 16 m x 12 m box at the origin.
    """
    if not recording.present.any():
        return np.array([0.0, 0.0]), np.array([16.0, 12.0])
    p = recording.positions[recording.present]
    return p.min(axis=0) - margin_m, p.max(axis=0) + margin_m


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
        end = float(rec.times_s()[-1])
        cut = (1.0 - self.val_fraction) * end
        if self.episode_time == "train":
            return 0.0, cut
        if self.episode_time == "val":
            return cut, end
        return 0.0, end

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
        frame, col = np.nonzero(rec.present[i0:i1])
        if len(frame) == 0:
            return rng.uniform(lo, hi)
        k = int(rng.integers(len(frame)))
        return rec.positions[i0 + frame[k], col[k]].astype(np.float64)

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
