"""``pause``: a pedestrian about to walk into the robot waits, then resumes its recording time-shifted by the wait.

SocNavBench's rule for its prerecorded pedestrians (Biswas et al. 2022: a pedestrian in collision with the robot
stops for a cool-down and then continues its recorded track, its clock shifted by the time it stood), made
anticipatory: the pedestrian waits *before* contact, while its next recorded position would be within the contact
distance plus :attr:`~envs.reaction.params.ReactionParams.pause_margin_m` of the robot and closer to it than where it
stands (so it never waits while walking away). A pedestrian that has waited ``w`` seconds is at
``recorded(t - w)``: an exact, time-shifted copy of its recording, present until its shifted track ends. It stops
and starts at once (no acceleration bound: the baseline as SocNavBench has it).
"""

from __future__ import annotations

import numpy as np

from envs.reaction.base import CrowdStep, ReactiveCrowd, StepInputs


class PausingCrowd(ReactiveCrowd):
    """``pause`` (see the module docstring). State: every pedestrian's accumulated wait, :attr:`shift_s`."""

    name = "pause"

    def _reset_state(self) -> None:
        self._shift = np.zeros(self._num)

    @property
    def shift_s(self) -> np.ndarray:
        """``(N,)`` seconds each pedestrian has waited so far (its recording's delay), a copy."""
        return self._shift.copy()

    def _quiet(self, dt_s: float, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray) -> CrowdStep | None:
        if (self._shift > 0.0).any():
            return None
        here = present[:-1].copy()
        here[0] = self._present
        moving = here & present[1:]  # (S, N)
        starts = self._starts(recorded, self._pos)
        at = robot[:-1, None, :]
        d_next = self._distance(recorded[1:], at)
        wait = moving & (d_next < self.contact_m + self.params.pause_margin_m) & (d_next < self._distance(starts, at))
        if wait.any():
            return None
        nxt, there = recorded[-1].copy(), present[-1].copy()
        deviation = np.where(there & present[-1], self._distance(nxt, recorded[-1]), 0.0)
        return CrowdStep(
            nxt,
            self._velocities(starts[-1], nxt, moving[-1], dt_s),
            there,
            np.zeros(self._num, dtype=bool),
            self._shift.copy(),
            deviation,
            self._zeros(),
        )

    def _step(self, inp: StepInputs) -> CrowdStep:
        dt_s, rec_next, pres_next, robot = inp.dt_s, inp.rec_next, inp.pres_next, inp.robot
        pos, here = self._pos, self._present
        nxt, there = rec_next.copy(), pres_next.copy()
        shifted = np.flatnonzero(self._shift > 0.0)
        if len(shifted):  # their own (shifted) clocks: one lookup for all of them
            assert self._tracks is not None
            times = self._t + dt_s - self._shift[shifted]
            spos, spres = self._tracks.positions_at(times)
            rows = np.arange(len(shifted))
            nxt[shifted] = spos[rows, shifted]
            there[shifted] = spres[rows, shifted]
        moving = here & there
        d_next = self._distance(nxt, robot)
        wait = moving & (d_next < self.contact_m + self.params.pause_margin_m) & (d_next < self._distance(pos, robot))
        if wait.any():
            nxt[wait] = pos[wait]
            self._shift[wait] += dt_s
        deviation = np.where(there & pres_next, self._distance(nxt, rec_next), 0.0)
        return CrowdStep(
            nxt,
            self._velocities(pos, nxt, moving, dt_s),
            there,
            wait,
            self._shift.copy(),
            deviation,
            self._zeros(),
        )
