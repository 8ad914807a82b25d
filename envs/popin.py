"""The pop-in rule: a pedestrian whose track begins on the robot is not materialised until it is clear of it.

A recording's track begins where annotation began. That may be on top of the robot: the person walked in
from outside the annotated area, or from occlusion, and did not materialise there. Replayed as it is, such a
start is a collision no policy could avoid (on univ, about 6-7 % of episodes). The environment applies one
rule, identical in every forecast arm:

    When a pedestrian *appears* in the world (its track begins, or resumes after a gap) with its centre
    closer than ``robot_radius_m + pedestrian_radius_m + POPIN_MARGIN_M`` to the robot's centre, it is a
    **ghost**: it has no contacts and no gap (physics, collision, discomfort, intrusion) and is absent for
    perception, until the first checkpoint at which its recorded position is at least that far from the
    robot. From then on it is an ordinary pedestrian until its track ends. Each such appearance is one
    **pop-in event**, counted per episode (``info["episode_metrics"]["popin_events"]``).

Checkpoints are the physics substep ends and the recording's annotation times. The world keeps interpolating
(physics uses the ghost state at the substep ends), while perception stays causal: the robot perceives a
pedestrian through the latest annotation at or before ``t`` only if the pedestrian was not a ghost at that
annotation's time, which depends on nothing annotated after it. On the 0.4 s recordings every control time is
an annotation time, so the two coincide. At reset the robot does not exist before ``t0``: a pedestrian on the
start at ``t0`` is a ghost for physics (it counts as a pop-in event) and, when ``t0`` falls between annotations
(``biwi_eth``), is still perceived through the annotation before ``t0``. Sampled starts keep
``start_clearance_m`` (1 m) from everyone at ``t0``, so this only happens with a ``start`` reset option.

Learned forecasts are computed per recording, independent of the robot (so they can be cached and shared):
a ghost still enters the predictor's input as a neighbour of the pedestrians the robot perceives, and once
it is perceived its forecast uses its annotated history, including the annotations from while it was a ghost.
Both are causal (nothing after ``t``); only the set of pedestrians the robot is told about changes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

import numpy as np

from envs.replay import TIME_TOL_S, Replay

#: Gap (metres, surface to surface) a newly appeared pedestrian needs from the robot to be materialised at once.
POPIN_MARGIN_M: Final[float] = 0.1


class PopInRule:
    """The pop-in rule's state over one episode (see the module docstring).

    Args:
        clear_m: centre distance at which a pedestrian counts as clear of the robot, metres
            (``robot_radius_m + pedestrian_radius_m + POPIN_MARGIN_M``).

    Attributes:
        ghost: ``(N,)`` bool: a ghost at the last checkpoint.
        events: pop-in events (ghosted appearances) so far in the episode.
    """

    def __init__(self, clear_m: float) -> None:
        self.clear_m = float(clear_m)
        self.ghost = np.zeros(0, dtype=bool)
        self._any_ghost = False
        self.events = 0
        self._present = np.zeros(0, dtype=bool)
        self._annotation: tuple[int, np.ndarray, np.ndarray] | None = None  # (index, columns, their ghost flags)

    def reset(self, replay: Replay, t0_s: float, robot: np.ndarray) -> None:
        """Start an episode at ``t0_s`` with the robot at ``robot`` ``(2,)`` metres: everyone present and close is a
        ghost (an event each)."""
        pos, present = replay.positions_at(np.array([t0_s]))
        self._present = present[0]
        self.ghost = present[0] & (self._distance(pos[0], robot) < self.clear_m)
        self.events = int(self.ghost.sum())
        self._any_ghost = self.events > 0
        self._annotation = None
        i = int(np.searchsorted(replay.times, t0_s + TIME_TOL_S, "right")) - 1
        if i >= 0 and abs(replay.times[i] - t0_s) <= TIME_TOL_S:
            self._annotation = (i, np.arange(len(self.ghost)), self.ghost.copy())

    def step(
        self,
        replay: Replay,
        times_s: np.ndarray,
        positions: np.ndarray,
        present: np.ndarray,
        robot: np.ndarray | Callable[[], np.ndarray],
    ) -> np.ndarray | None:
        """Advance over one control step.

        Args:
            replay: the episode's replay.
            times_s: ``(S + 1,)`` substep boundaries, seconds; the first is the last checkpoint already processed.
            positions: ``(S + 1, N, 2)`` replay positions at ``times_s``, metres.
            present: ``(S + 1, N)`` replay presence at ``times_s``.
            robot: ``(S + 1, 2)`` robot centre at ``times_s`` (moving linearly in between), metres, or a function
                returning it (called only when a pedestrian appears during the step).

        Returns:
            ``(S + 1, N)`` bool: ghosts at each boundary (row 0: the state before the step); None when there is
            no ghost during the step (the common case).
        """
        times = np.asarray(times_s, dtype=np.float64)
        num = len(times)
        lo, hi = np.searchsorted(replay.times, (times[0] + TIME_TOL_S, times[-1] + TIME_TOL_S), "right")
        inside = hi > lo and not (hi - lo == 1 and abs(replay.times[lo] - times[-1]) <= TIME_TOL_S)
        if not inside and not self._any_ghost:  # fast path: annotations at most at the step's end, no ghost now
            near = np.flatnonzero((present[1:] & ~present[:-1]).any(axis=0))
            if len(near):
                robot = robot() if callable(robot) else robot
                near = near[(self._distance(positions[1:, near], robot[1:, None, :]) < self.clear_m).any(axis=0)]
            if len(near) == 0:
                self._present = present[-1].copy()
                if hi > lo:
                    self._annotation = (int(lo), near, np.zeros(0, dtype=bool))
                return None
        robot = robot() if callable(robot) else robot
        annotation = np.full(num, -1, dtype=np.int64)
        all_pos, all_present, all_robot, boundary = positions, present, robot, np.ones(num, dtype=bool)
        if hi > lo:
            ann_t = replay.times[lo:hi]  # annotations in (times[0], times[-1]]
            gap = np.abs(times[:, None] - ann_t[None, :])  # (S + 1, n)
            on_boundary = gap.min(axis=0) <= TIME_TOL_S
            annotation[gap[:, on_boundary].argmin(axis=0)] = np.arange(lo, hi)[on_boundary]
            if not on_boundary.all():  # annotations between substep ends (biwi_eth): checkpoints of their own
                et, ei = ann_t[~on_boundary], np.arange(lo, hi)[~on_boundary]
                epos, epres = replay.positions_at(et)
                k = np.searchsorted(times, et) - 1  # the substep holding each
                w = ((et - times[k]) / (times[k + 1] - times[k]))[:, None]
                order = np.argsort(np.concatenate([times, et]), kind="stable")
                all_pos = np.concatenate([positions, epos])[order]
                all_present = np.concatenate([present, epres])[order]
                all_robot = np.concatenate([robot, robot[k] + w * (robot[k + 1] - robot[k])])[order]
                annotation = np.concatenate([annotation, ei])[order]
                boundary = np.concatenate([boundary, np.zeros(len(et), dtype=bool)])[order]
        out = np.zeros((num, present.shape[1]), dtype=bool)
        out[0] = self.ghost
        close = self._distance(all_pos, all_robot[:, None, :]) < self.clear_m  # (C, N)
        # only pedestrians that are ghosts now or appear close to the robot during the step can be ghosts in it
        # (checkpoint 0 is the last one of the previous step: its presence is the state's)
        cols = np.flatnonzero(self.ghost | (all_present[1:] & ~all_present[:-1] & close[1:]).any(axis=0))
        close = close[:, cols]
        ghost, was = self.ghost[cols], self._present[cols]
        self._present = all_present[-1].copy()
        row = 1
        for c in range(1, len(all_present)):
            now = all_present[c, cols]
            appear = now & ~was
            self.events += int(np.count_nonzero(appear & close[c]))
            ghost = now & close[c] & (ghost | appear)
            was = now
            if annotation[c] >= 0:
                self._annotation = (int(annotation[c]), cols, ghost.copy())
            if boundary[c]:
                out[row, cols] = ghost
                row += 1
        self.ghost = np.zeros_like(self.ghost)
        self.ghost[cols] = ghost
        self._any_ghost = bool(ghost.any())
        return out

    def dropped(self, annotation_index: int, num: int) -> np.ndarray:
        """``(num,)`` bool: pedestrians perception leaves out when it reports annotation ``annotation_index`` (the
        ghosts at that annotation's time; nobody for an annotation before the episode's start)."""
        out = np.zeros(num, dtype=bool)
        if self._annotation is not None and self._annotation[0] == annotation_index:
            out[self._annotation[1]] = self._annotation[2]
        return out

    @staticmethod
    def _distance(points: np.ndarray, robot: np.ndarray) -> np.ndarray:
        return np.hypot(points[..., 0] - robot[..., 0], points[..., 1] - robot[..., 1])
