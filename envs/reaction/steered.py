"""Replay-then-model: what ``orca`` and ``social_force`` share (trigger, preferred velocity, bounds, rejoining).

Every pedestrian follows its recording exactly (the positions are the recorded ones, bit for bit) until the robot's
centre comes within :attr:`~envs.reaction.params.ReactionParams.trigger_distance_m` of its own. From then on it is
*reacting*: a model (:meth:`SteeredCrowd._model_velocities`) chooses its velocity from

* its preferred velocity ``v_rec + (p_rec - p) / lookahead_s``, capped at ``max_speed_mps``: towards where its
  recording would be ``lookahead_s`` later at its recorded velocity, so off its track the deviation decays with
  time constant ``lookahead_s`` and on it the pedestrian walks exactly as recorded (``v_rec`` is the recorded
  velocity over the step, ``p_rec`` the recorded position now);
* the robot (position and velocity: it moves as it does, no model steers it);
* its neighbours within ``neighbor_distance_m``: the other reacting pedestrians (as they move) and the
  non-reacting ones (as recorded: they are never steered).

The model's velocity is then bounded: its change over the step by ``max_accel_mps2 * dt``, its norm by
``max_speed_mps`` (or, for a pedestrian triggered while faster than that, by its speed at the step's start, so it
only slows down). The pedestrian moves ``p += v dt``.

It returns to its recording when the robot is farther than ``release_distance_m`` and the velocity that lands it
exactly on its recorded position at the step's end is within ``on_track_tolerance_m / dt`` of the model's and
within both bounds: that step's velocity is the landing one, and from the next step on it follows its recording
again, bit for bit. So a pedestrian never jumps: every reacting step respects both bounds, the landing one too.

A pedestrian whose recorded track ends while it reacts leaves where it is; one that appears starts on its
recording. Presence is always the recording's.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

import numpy as np

from envs.reaction.base import CrowdPath, CrowdStep, ReactiveCrowd, StepInputs


@dataclass(slots=True)
class Neighbourhood:
    """What a model sees at one step: the reacting pedestrians and their neighbours (arrays over them).

    Attributes:
        reacting: ``(m,)`` rows of the reacting pedestrians.
        positions: ``(m, 2)`` their positions, metres.
        velocities: ``(m, 2)`` their velocities at the step's start, m/s (over the previous step; for one that was
            not present then, its recorded velocity over this step).
        preferred: ``(m, 2)`` their preferred velocities, m/s.
        recorded: ``(m, 2)`` their recorded positions now, metres.
        recorded_change: ``(m, 2)`` the change of their recorded velocity from the step before to this one, m/s (0
            for one not present at both ends of the step before).
        others: ``(k,)`` rows of the non-reacting pedestrians within ``neighbor_distance_m`` of a reacting one.
        other_positions: ``(k, 2)`` metres (recorded).
        other_velocities: ``(k, 2)`` m/s (recorded, over the step).
        robot: ``(2,)`` the robot's centre, metres.
        robot_velocity: ``(2,)`` m/s.
        dt_s: the step, seconds.
    """

    reacting: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    preferred: np.ndarray
    recorded: np.ndarray
    recorded_change: np.ndarray
    others: np.ndarray
    other_positions: np.ndarray
    other_velocities: np.ndarray
    robot: np.ndarray
    robot_velocity: np.ndarray
    dt_s: float


class SteeredCrowd(ReactiveCrowd):
    """Replay-then-model (see the module docstring); subclasses supply the model's velocities."""

    def _reset_state(self) -> None:
        self._reacting = np.zeros(self._num, dtype=bool)
        self._vel = np.zeros((self._num, 2))
        self._vel_known = np.zeros(self._num, dtype=bool)  # present at both ends of the previous step
        self._rec_vel = np.zeros((self._num, 2))  # recorded velocities over the previous step (where _vel_known)

    @property
    def reacting(self) -> np.ndarray:
        """``(N,)`` bool: moved by the model now (a copy)."""
        return self._reacting.copy()

    @abstractmethod
    def _model_velocities(self, hood: Neighbourhood) -> np.ndarray:
        """``(m, 2)`` the model's velocities of the reacting pedestrians for the step, m/s (bounded afterwards)."""

    def _quiet(self, dt_s: float, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray) -> CrowdStep | None:
        if self._reacting.any():
            return None
        moving = present[:-1] & present[1:]  # (S, N)
        d_robot = self._distance(self._starts(recorded, self._pos), robot[:-1, None, :])
        if (moving & (d_robot < self.params.trigger_distance_m)).any():
            return None
        rec_vel = self._velocities(recorded[-2], recorded[-1], moving[-1], dt_s)
        self._vel, self._vel_known, self._rec_vel = rec_vel, moving[-1], rec_vel
        zeros = self._zeros()
        return CrowdStep(recorded[-1].copy(), rec_vel, present[-1].copy(), self._reacting.copy(), zeros, zeros, zeros)

    def _step(self, inp: StepInputs) -> CrowdStep:
        moving = inp.pres_now & inp.pres_next
        triggered = moving & (self._distance(self._pos, inp.robot) < self.params.trigger_distance_m)
        rec_vel = self._velocities(inp.rec_now, inp.rec_next, moving, inp.dt_s)
        new = inp.rec_next.copy()
        idx = self._substep(
            inp.dt_s, self._pos, new, inp.rec_now, inp.rec_next, rec_vel, moving, triggered, inp.robot, inp.robot_vel
        )
        return self._last(new, inp.pres_next, idx, inp.rec_next)

    def _steps(
        self, dt_s: float, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray, robot_velocities: np.ndarray
    ) -> CrowdPath:
        """``S`` steps: what does not depend on the model is computed for all of them at once, with the same floats
        element by element (as :meth:`_step` computes it for one); only the reacting pedestrians are stepped one step
        at a time (:meth:`_substep`)."""
        steps = len(recorded) - 1
        moving = present[:-1] & present[1:]  # (S, N)
        # triggered at a step's start by the robot's distance. A pedestrian not reacting then is where the state has it
        # at the first step and at its recorded floats at the others (a step leaves it there, landing included); for
        # one reacting then the test changes nothing (it stays reacting while present at both ends of the step)
        d_robot = self._distance(self._starts(recorded, self._pos), robot[:-1, None, :])
        triggered = moving & (d_robot < self.params.trigger_distance_m)
        rec_vel = self._velocities(recorded[:-1], recorded[1:], moving, dt_s)  # (S, N, 2)
        positions = recorded.copy()
        positions[0] = self._pos
        pres = present.copy()
        pres[0] = self._present
        idx = np.zeros(0, dtype=np.int64)
        for k in range(steps):
            idx = self._substep(
                dt_s,
                positions[k],
                positions[k + 1],
                recorded[k],
                recorded[k + 1],
                rec_vel[k],
                moving[k],
                triggered[k],
                robot[k],
                robot_velocities[k],
            )
        return CrowdPath(positions, pres, self._last(positions[steps].copy(), present[steps], idx, recorded[steps]))

    def _substep(
        self,
        dt_s: float,
        pos: np.ndarray,
        new: np.ndarray,
        rec_now: np.ndarray,
        rec_next: np.ndarray,
        rec_vel: np.ndarray,
        moving: np.ndarray,
        triggered: np.ndarray,
        robot: np.ndarray,
        robot_vel: np.ndarray,
    ) -> np.ndarray:
        """One step from ``pos`` ``(N, 2)``: the state (reacting flags, velocities) moved on, the reacting pedestrians'
        positions at the step's end written into ``new`` (which holds ``rec_next`` elsewhere). ``triggered``: ``(N,)``
        present at both ends and within the trigger distance at the step's start (for one not reacting then). Returns
        the rows that reacted during the step."""
        prm = self.params
        # the state: reacting pedestrians that leave stop reacting; others are triggered by the robot's distance
        reacting = self._reacting
        reacting &= moving
        reacting |= triggered
        idx = np.flatnonzero(reacting)
        if not len(idx):  # everyone as recorded
            self._vel, self._vel_known, self._rec_vel = rec_vel, moving, rec_vel
            return idx
        p, rv_idx = pos[idx], rec_vel[idx]
        known = self._vel_known[idx, None]
        v0 = np.where(known, self._vel[idx], rv_idx)
        change = np.where(known, rv_idx - self._rec_vel[idx], 0.0)
        pref = _capped(rv_idx + (rec_now[idx] - p) / prm.lookahead_s, prm.max_speed_mps)
        hood = self._neighbourhood(idx, p, v0, pref, change, rec_now, rec_vel, moving, robot, robot_vel, dt_s)
        speed_cap = np.maximum(prm.max_speed_mps, np.hypot(v0[:, 0], v0[:, 1]))
        v = _bounded(self._model_velocities(hood), v0, prm.max_accel_mps2 * dt_s, speed_cap)
        # back to the recording: landing exactly on it is within the bounds and close to the model's velocity
        target = rec_next[idx]
        v_land = (target - p) / dt_s
        land = (
            (self._distance(p, robot) > prm.release_distance_m)
            & (_norm(v_land - v) <= prm.on_track_tolerance_m / dt_s)
            & (_norm(v_land - v0) <= prm.max_accel_mps2 * dt_s)
            & (_norm(v_land) <= speed_cap)
        )
        new[idx] = np.where(land[:, None], target, p + v * dt_s)
        vel = rec_vel.copy()
        vel[idx] = np.where(land[:, None], v_land, v)
        reacting[idx[land]] = False
        self._vel, self._vel_known, self._rec_vel = vel, moving, rec_vel
        return idx

    def _last(self, positions: np.ndarray, present: np.ndarray, idx: np.ndarray, recorded: np.ndarray) -> CrowdStep:
        """The :class:`CrowdStep` of a step that ended at ``positions`` (kept), ``idx`` reacting during it."""
        deviation = self._zeros()
        if len(idx):
            deviation[idx] = _norm(positions[idx] - recorded[idx])
        return CrowdStep(
            positions, self._vel, present.copy(), self._reacting.copy(), self._zeros(), deviation, deviation.copy()
        )

    def _neighbourhood(
        self,
        idx: np.ndarray,
        p: np.ndarray,
        v0: np.ndarray,
        pref: np.ndarray,
        change: np.ndarray,
        rec_now: np.ndarray,
        rec_vel: np.ndarray,
        moving: np.ndarray,
        robot: np.ndarray,
        robot_vel: np.ndarray,
        dt_s: float,
    ) -> Neighbourhood:
        """The reacting pedestrians ``idx`` and the non-reacting ones within the neighbour distance of any of them."""
        others = np.flatnonzero(moving & ~self._reacting)
        q = rec_now[others]
        if len(others):
            diff = q[:, None, :] - p[None, :, :]
            near = np.einsum("kmc,kmc->km", diff, diff).min(axis=1) < self.params.neighbor_distance_m**2
            others, q = others[near], q[near]
        return Neighbourhood(idx, p, v0, pref, rec_now[idx], change, others, q, rec_vel[others], robot, robot_vel, dt_s)


def _norm(v: np.ndarray) -> np.ndarray:
    return np.hypot(v[..., 0], v[..., 1])


def _capped(v: np.ndarray, cap: float | np.ndarray) -> np.ndarray:
    """``v`` ``(m, 2)`` scaled down where its norm exceeds ``cap`` (a number or ``(m,)``)."""
    scale = np.minimum(1.0, cap / np.maximum(_norm(v), 1e-12))
    return v * scale[:, None]


def _bounded(v: np.ndarray, v0: np.ndarray, max_change: float, speed_cap: np.ndarray) -> np.ndarray:
    """``v`` with its change from ``v0`` capped at ``max_change``, then its norm at ``speed_cap`` ``(m,)``.

    The second cap is the projection onto a disk that holds ``v0`` (``speed_cap >= |v0|``), which brings ``v`` no
    farther from ``v0``: both bounds hold."""
    return _capped(v0 + _capped(v - v0, max_change), speed_cap)
