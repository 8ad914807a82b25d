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
        self.events = 0
        self._present = np.zeros(0, dtype=bool)
        self._annotation: tuple[int, np.ndarray] | None = None

    def reset(self, replay: Replay, t0_s: float, robot: np.ndarray) -> None:
        """Start an episode at ``t0_s`` with the robot at ``robot`` ``(2,)`` metres: everyone present and close is a
        ghost (an event each)."""
        pos, present = replay.positions_at(np.array([t0_s]))
        self._present = present[0]
        self.ghost = present[0] & (self._distance(pos[0], robot) < self.clear_m)
        self.events = int(self.ghost.sum())
        self._annotation = None
        i = int(np.searchsorted(replay.times, t0_s + TIME_TOL_S, "right")) - 1
        if i >= 0 and abs(replay.times[i] - t0_s) <= TIME_TOL_S:
            self._annotation = (i, self.ghost.copy())

    def step(
        self, replay: Replay, times_s: np.ndarray, positions: np.ndarray, present: np.ndarray, robot: np.ndarray
    ) -> np.ndarray:
        """Advance over one control step.

        Args:
            replay: the episode's replay.
            times_s: ``(S + 1,)`` substep boundaries, seconds; the first is the last checkpoint already processed.
            positions: ``(S + 1, N, 2)`` replay positions at ``times_s``, metres.
            present: ``(S + 1, N)`` replay presence at ``times_s``.
            robot: ``(S + 1, 2)`` robot centre at ``times_s`` (moving linearly in between), metres.

        Returns:
            ``(S + 1, N)`` bool: ghosts at each boundary (row 0: the state before the step).
        """
        times = np.asarray(times_s, dtype=np.float64)
        num = len(times)
        lo = int(np.searchsorted(replay.times, times[0] + TIME_TOL_S, "right"))
        hi = int(np.searchsorted(replay.times, times[-1] + TIME_TOL_S, "right"))
        annotation = np.full(num, -1, dtype=np.int64)
        extra_t, extra_i = [], []
        for i in range(lo, hi):
            ta = float(replay.times[i])
            k = int(np.argmin(np.abs(times - ta)))
            if abs(times[k] - ta) <= TIME_TOL_S:
                annotation[k] = i
            else:
                extra_t.append(ta)
                extra_i.append(i)
        if extra_t:  # annotations between substep ends (biwi_eth): checkpoints of their own
            et = np.array(extra_t)
            epos, epres = replay.positions_at(et)
            k = np.searchsorted(times, et) - 1  # the substep holding each
            w = ((et - times[k]) / (times[k + 1] - times[k]))[:, None]
            erobot = robot[k] + w * (robot[k + 1] - robot[k])
            order = np.argsort(np.concatenate([times, et]), kind="stable")
            all_pos = np.concatenate([positions, epos])[order]
            all_present = np.concatenate([present, epres])[order]
            all_robot = np.concatenate([robot, erobot])[order]
            all_annotation = np.concatenate([annotation, np.array(extra_i, dtype=np.int64)])[order]
            boundary = np.concatenate([np.ones(num, dtype=bool), np.zeros(len(et), dtype=bool)])[order]
        else:
            all_pos, all_present, all_robot, all_annotation = positions, present, robot, annotation
            boundary = np.ones(num, dtype=bool)
        close = self._distance(all_pos, all_robot[:, None, :]) < self.clear_m  # (C, N)
        out = np.empty((num, present.shape[1]), dtype=bool)
        out[0] = self.ghost
        row = 1
        for c in range(1, len(all_present)):
            now = all_present[c]
            appear = now & ~self._present
            self.events += int(np.count_nonzero(appear & close[c]))
            self.ghost = now & close[c] & (self.ghost | appear)
            self._present = now
            if all_annotation[c] >= 0:
                self._annotation = (int(all_annotation[c]), self.ghost.copy())
            if boundary[c]:
                out[row] = self.ghost
                row += 1
        return out

    def dropped(self, annotation_index: int, num: int) -> np.ndarray:
        """``(num,)`` bool: pedestrians perception leaves out when it reports annotation ``annotation_index`` (the
        ghosts at that annotation's time; nobody for an annotation before the episode's start)."""
        if self._annotation is not None and self._annotation[0] == annotation_index:
            return self._annotation[1]
        return np.zeros(num, dtype=bool)

    @staticmethod
    def _distance(points: np.ndarray, robot: np.ndarray) -> np.ndarray:
        return np.hypot(points[..., 0] - robot[..., 0], points[..., 1] - robot[..., 1])
