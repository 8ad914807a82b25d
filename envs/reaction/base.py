"""The interface every reaction model implements, and ``none`` (the recording, untouched).

A reaction model moves the pedestrians of one episode step by step. At each step it is given what the recording
says (every pedestrian's recorded position at the step's start and end, and presence), where the robot is and how
it moves, and returns where the pedestrians actually are at the step's end. It keeps per pedestrian whether it is
reacting, its time shift (``pause``) and its distance from its recording. It knows nothing of gymnasium, pymunk,
forecasts or the robot's goal: pedestrians see the robot's position and velocity, nothing else.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar, Final, Protocol

import numpy as np

from envs.reaction.params import ReactionParams

#: Two times closer than this are the same instant, seconds (as :data:`envs.replay.TIME_TOL_S`).
_TIME_TOL_S: Final[float] = 1e-6


class RecordedTracks(Protocol):
    """What a model reads of the recording beyond the two instants it is given (``pause`` reads its pedestrians'
    time-shifted positions). :class:`envs.replay.Replay` is one."""

    @property
    def num_pedestrians(self) -> int: ...

    def positions_at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Recorded positions ``(T, N, 2)`` metres and presence ``(T, N)`` at ``times_s`` ``(T,)`` seconds."""
        ...


@dataclass(frozen=True)
class CrowdStep:
    """The pedestrians at the end of one step.

    Attributes:
        positions: ``(N, 2)`` metres, world frame (meaningless where not present).
        velocities: ``(N, 2)`` m/s over the step: ``(positions - positions before) / dt`` where present at both
            ends, else 0.
        present: ``(N,)`` bool. The recording's presence, except for ``pause``, whose time-shifted pedestrians stay
            until their shifted tracks end.
        reacting: ``(N,)`` bool: the model moved the pedestrian during the step (not as recorded) and has not handed
            it back to its recording at the step's end (``pause``: it waited during the step).
        shift_s: ``(N,)`` seconds: the pedestrian follows its recording ``shift_s`` late (``pause``; 0 otherwise).
        deviation_m: ``(N,)`` metres from the recorded position at the same time (0 where either is absent).
        offtrack_m: ``(N,)`` metres from the position of its time-shifted recording, the track it returns to (equals
            ``deviation_m`` for unshifted models; 0 for ``pause``, which never leaves its shifted track).
    """

    positions: np.ndarray
    velocities: np.ndarray
    present: np.ndarray
    reacting: np.ndarray
    shift_s: np.ndarray
    deviation_m: np.ndarray
    offtrack_m: np.ndarray


@dataclass(frozen=True)
class CrowdPath:
    """The pedestrians over several consecutive steps (one control step of ``S`` physics substeps).

    Attributes:
        positions: ``(S + 1, N, 2)`` metres at the step boundaries, the state before the first step first.
        present: ``(S + 1, N)`` bool.
        last: the last step's :class:`CrowdStep` (reacting flags, shifts and deviations at the end).
    """

    positions: np.ndarray
    present: np.ndarray
    last: CrowdStep


@dataclass(slots=True)
class StepInputs:
    """What a model's step is given (checked by :meth:`ReactiveCrowd.step`): see its arguments.

    Attributes:
        dt_s: seconds.
        rec_now: ``(N, 2)`` recorded positions at the step's start, metres; pres_now: ``(N,)``.
        rec_next: ``(N, 2)`` recorded positions at its end; pres_next: ``(N,)``.
        robot: ``(2,)`` the robot's centre at the start, metres; robot_vel: ``(2,)`` its velocity, m/s.
    """

    dt_s: float
    rec_now: np.ndarray
    pres_now: np.ndarray
    rec_next: np.ndarray
    pres_next: np.ndarray
    robot: np.ndarray
    robot_vel: np.ndarray


class ReactiveCrowd(ABC):
    """The pedestrians of one episode under a reaction model (one instance per world; a batched environment holds
    one per episode).

    Call :meth:`reset` at the episode's start, then :meth:`step` once per step of length ``dt_s`` (a physics
    substep), in time order, or :meth:`advance` once per control step. Deterministic: no randomness.

    Args:
        params: the models' constants.
        robot_radius_m: the robot's radius (the environment's), metres.
        pedestrian_radius_m: the pedestrians' radius (the environment's), metres; the robot and a pedestrian are in
            contact when their centres are closer than the sum of the two radii.
    """

    name: ClassVar[str]

    def __init__(self, params: ReactionParams, robot_radius_m: float, pedestrian_radius_m: float) -> None:
        self.params = params
        self.robot_radius_m = float(robot_radius_m)
        self.contact_m = self.robot_radius_m + float(pedestrian_radius_m)
        self._tracks: RecordedTracks | None = None
        self._t = 0.0
        self._num = 0

    # ------------------------------------------------------------------ state

    def reset(self, tracks: RecordedTracks, t_s: float) -> None:
        """Start an episode at ``t_s`` (seconds, the recording's clock): every pedestrian on its recording."""
        self._tracks = tracks
        self._t = float(t_s)
        self._num = int(tracks.num_pedestrians)
        pos, present = tracks.positions_at(np.array([self._t]))
        self._pos = np.array(pos[0], dtype=np.float64)
        self._present = np.array(present[0], dtype=bool)
        self._reset_state()

    def _reset_state(self) -> None:  # noqa: B027 - a hook: ``none`` has no state of its own
        """Model state at the start of an episode (after :attr:`_pos`, :attr:`_present` are set)."""

    def clone(self) -> ReactiveCrowd:
        """An independent copy of the crowd in its current state (sharing only the read-only recording and the
        constants), to roll the model forward for a candidate robot path without touching this one."""
        twin = copy.copy(self)
        for key, value in vars(self).items():
            if isinstance(value, np.ndarray):
                setattr(twin, key, value.copy())
        return twin

    @property
    def time_s(self) -> float:
        """The time of the current state, seconds."""
        return self._t

    @property
    def positions(self) -> np.ndarray:
        """``(N, 2)`` actual positions now, metres (a copy)."""
        return self._pos.copy()

    @property
    def present(self) -> np.ndarray:
        """``(N,)`` actual presence now (a copy)."""
        return self._present.copy()

    # ------------------------------------------------------------------ stepping

    def step(
        self,
        t_s: float,
        dt_s: float,
        recorded_now: np.ndarray,
        present_now: np.ndarray,
        recorded_next: np.ndarray,
        present_next: np.ndarray,
        robot_position: np.ndarray,
        robot_velocity: np.ndarray,
    ) -> CrowdStep:
        """Move the pedestrians from ``t_s`` to ``t_s + dt_s``.

        Args:
            t_s: the current time, seconds (the time of the current state: :attr:`time_s`).
            dt_s: the step's length, seconds (> 0).
            recorded_now: ``(N, 2)`` recorded positions at ``t_s``, metres.
            present_now: ``(N,)`` recorded presence at ``t_s``.
            recorded_next: ``(N, 2)`` recorded positions at ``t_s + dt_s``, metres.
            present_next: ``(N,)`` recorded presence at ``t_s + dt_s``.
            robot_position: ``(2,)`` the robot's centre at ``t_s``, metres.
            robot_velocity: ``(2,)`` the robot's velocity as the pedestrians see it at ``t_s``, m/s (the robot is not
                steered by any model: it moves as the environment says).

        Returns:
            the pedestrians at ``t_s + dt_s``.
        """
        if self._tracks is None:
            raise RuntimeError(f"{type(self).__name__}: call reset() before step()")
        if abs(t_s - self._t) > _TIME_TOL_S:
            raise ValueError(f"{type(self).__name__}.step at t_s = {t_s!r} s, but the crowd is at {self._t!r} s")
        if not (dt_s > 0.0):
            raise ValueError(f"{type(self).__name__}.step: dt_s must be > 0 seconds, got {dt_s!r}")
        self._t = float(t_s)  # the caller's clock is the reference (no drift from summing steps)
        n = self._num
        for what, arr, shape in (
            ("recorded_now", recorded_now, (n, 2)),
            ("present_now", present_now, (n,)),
            ("recorded_next", recorded_next, (n, 2)),
            ("present_next", present_next, (n,)),
            ("robot_position", robot_position, (2,)),
            ("robot_velocity", robot_velocity, (2,)),
        ):
            if np.shape(arr) != shape:
                raise ValueError(f"{type(self).__name__}.step: {what} must have shape {shape}, got {np.shape(arr)}")
        out = self._step(
            StepInputs(
                float(dt_s),
                np.asarray(recorded_now, dtype=np.float64),
                np.asarray(present_now, dtype=bool),
                np.asarray(recorded_next, dtype=np.float64),
                np.asarray(present_next, dtype=bool),
                np.asarray(robot_position, dtype=np.float64),
                np.asarray(robot_velocity, dtype=np.float64),
            )
        )
        self._t += dt_s
        self._pos = out.positions
        self._present = out.present
        return out

    @abstractmethod
    def _step(self, inp: StepInputs) -> CrowdStep:
        """One step (arguments checked; :attr:`_pos`, :attr:`_present` are the state at its start)."""

    def advance(
        self,
        t_s: float,
        dt_s: float,
        recorded: np.ndarray,
        present: np.ndarray,
        robot_path: np.ndarray,
        robot_velocities: np.ndarray,
    ) -> CrowdPath:
        """:meth:`step` ``S`` times (a control step's physics substeps of ``dt_s``), at once.

        Args:
            t_s: the current time, seconds (:attr:`time_s`); step ``k`` starts at ``t_s + k dt_s``.
            dt_s: the length of each step, seconds.
            recorded: ``(S + 1, N, 2)`` recorded positions at ``t_s + k dt_s``, metres.
            present: ``(S + 1, N)`` recorded presence there.
            robot_path: ``(S + 1, 2)`` the robot's centre there (the last one is not used), metres.
            robot_velocities: ``(S, 2)`` the robot's velocity as the pedestrians see it at each of the first ``S``
                times, m/s.

        Returns:
            the actual positions and presence at ``t_s + k dt_s``, ``k = 0..S`` (row 0: the current state), and the
            last step.

        When the model would leave everyone on the recording over all ``S`` steps (:meth:`_quiet`, checked at once over
        the steps: nobody reacting, nobody triggered), the recording is returned without stepping; otherwise a model
        may take the ``S`` steps in one call (:meth:`_steps`, sparing the per-step work :meth:`step` repeats). Both give
        the same result and state as stepping, bit for bit (``tests/envs/reaction/test_quiet.py``).
        """
        steps = len(recorded) - 1
        if steps < 1:
            raise ValueError(
                f"{type(self).__name__}.advance needs at least 2 rows of recorded positions, got {steps + 1}"
            )
        if self.quiet_advance and self._tracks is not None and abs(t_s - self._t) <= _TIME_TOL_S:
            rec = np.asarray(recorded, dtype=np.float64)
            pres_in = np.asarray(present, dtype=bool)
            robot = np.asarray(robot_path, dtype=np.float64)
            if (
                rec.shape == (steps + 1, self._num, 2)
                and pres_in.shape == rec.shape[:2]
                and robot.shape == (steps + 1, 2)
            ):
                last_quiet = self._quiet(dt_s, rec, pres_in, robot)
                if last_quiet is not None:
                    return self._replayed(t_s, dt_s, rec, pres_in, last_quiet)
                seen = np.asarray(robot_velocities, dtype=np.float64)
                if seen.shape == (steps, 2) and dt_s > 0.0:
                    path = self._steps(dt_s, rec, pres_in, robot, seen)
                    if path is not None:
                        self._moved(t_s, dt_s, steps, path.last)
                        return path
        positions = np.empty((steps + 1, self._num, 2))
        pres = np.empty((steps + 1, self._num), dtype=bool)
        positions[0], pres[0] = self._pos, self._present
        last = None
        for k in range(steps):  # at t_s + k dt_s, as the environment's substep times
            last = self.step(
                t_s + k * dt_s,
                dt_s,
                recorded[k],
                present[k],
                recorded[k + 1],
                present[k + 1],
                robot_path[k],
                robot_velocities[k],
            )
            positions[k + 1], pres[k + 1] = last.positions, last.present
        assert last is not None
        return CrowdPath(positions, pres, last)

    #: :meth:`advance` skips the steps in which the model would leave everyone on the recording and takes the others in
    #: one call where the model can (False: always :meth:`step` ``S`` times, the reference).
    quiet_advance: ClassVar[bool] = True

    def _quiet(self, dt_s: float, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray) -> CrowdStep | None:
        """The last :class:`CrowdStep` of ``S`` steps in which the model leaves everyone on the recording, with the
        model's own state set as after them, or None (the steps must be taken). Arguments as :meth:`advance` (checked
        arrays). Default: never quiet."""
        return None

    def _steps(
        self, dt_s: float, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray, robot_velocities: np.ndarray
    ) -> CrowdPath | None:
        """``S`` steps in one call, as :meth:`step` ``S`` times gives them (bit for bit), with the model's own state set
        as after them (:attr:`_t`, :attr:`_pos`, :attr:`_present` are set by :meth:`advance`), or None (step one by
        one). Arguments as :meth:`advance` (checked arrays). Default: None."""
        return None

    def _replayed(
        self, t_s: float, dt_s: float, recorded: np.ndarray, present: np.ndarray, last: CrowdStep
    ) -> CrowdPath:
        """The :class:`CrowdPath` of ``S`` quiet steps (everyone at the recorded floats), and the state after them."""
        steps = len(recorded) - 1
        positions = recorded.copy()
        pres = present.copy()
        positions[0], pres[0] = self._pos, self._present
        self._moved(t_s, dt_s, steps, last)
        return CrowdPath(positions, pres, last)

    def _moved(self, t_s: float, dt_s: float, steps: int, last: CrowdStep) -> None:
        """The state after ``steps`` steps from ``t_s`` ending with ``last``: the time as the last of the steps leaves
        it (:meth:`step`), the positions and presence at its end."""
        self._t = (t_s + (steps - 1) * dt_s) + dt_s
        self._pos = last.positions
        self._present = last.present

    @staticmethod
    def _starts(recorded: np.ndarray, now: np.ndarray) -> np.ndarray:
        """``(S, N, 2)`` positions at the start of each of ``S`` quiet steps: ``now`` (the state), then the recorded
        ones (a quiet step leaves its pedestrians at the recorded floats)."""
        starts = recorded[:-1].copy()
        starts[0] = now
        return starts

    # ------------------------------------------------------------------ helpers for the models

    def _zeros(self) -> np.ndarray:
        return np.zeros(self._num)

    @staticmethod
    def _velocities(before: np.ndarray, after: np.ndarray, moving: np.ndarray, dt_s: float) -> np.ndarray:
        """``(after - before) / dt`` where ``moving``, else 0 (``(..., N, 2)`` and ``(..., N)``)."""
        return np.where(moving[..., None], (after - before) / dt_s, 0.0)

    @staticmethod
    def _distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1])


class ReplayedCrowd(ReactiveCrowd):
    """``none``: every pedestrian moves exactly as recorded (the positions returned are the recorded ones)."""

    name = "none"

    def _quiet(self, dt_s: float, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray) -> CrowdStep | None:
        zeros = self._zeros()
        moving = present[-2] & present[-1]
        vel = self._velocities(recorded[-2], recorded[-1], moving, dt_s)
        return CrowdStep(
            recorded[-1].copy(), vel, present[-1].copy(), np.zeros(self._num, dtype=bool), zeros, zeros, zeros
        )

    def _step(self, inp: StepInputs) -> CrowdStep:
        zeros = self._zeros()
        return CrowdStep(
            inp.rec_next,
            self._velocities(inp.rec_now, inp.rec_next, inp.pres_now & inp.pres_next, inp.dt_s),
            inp.pres_next,
            np.zeros(self._num, dtype=bool),
            zeros,
            zeros,
            zeros,
        )
