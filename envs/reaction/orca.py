"""``orca``: replay-then-model with ORCA (van den Berg et al. 2011) from the RVO2 library, through ``pyrvo``.

At each step a fresh RVO2 simulator holds the reacting pedestrians, their non-reacting neighbours and the robot.
Only the reacting pedestrians' new velocities are read; everybody else is an agent whose velocity is what it does
(the robot's own velocity, the recorded velocity of a non-reacting pedestrian), so that ORCA's constraints see them
as they move, and whatever the solver would make of them is discarded.

**Responsibility.** RVO2 splits the avoidance of every pair in halves (each agent assumes the other takes half of
the velocity change), with no way to weight a pair. Neither the robot nor a non-reacting pedestrian takes its half.
We keep RVO2's reciprocal rule, as CrowdNav does for its visible robot (Chen et al. 2019: the humans' ORCA counts
the robot as one more agent while the robot follows its own policy), rather than emulate full responsibility: ORCA
is solved again at every step from the velocities actually taken, so a pedestrian whose counterpart did
not take its half faces the remaining conflict at the next substep and takes more of it. The tests measure the
result: pedestrians walking head-on at a standing robot keep the contact distance up to a few millimetres
(``tests/envs/reaction/test_avoidance.py``).

**Radii.** ORCA keeps the sum of two agents' radii between their centres. Pedestrians get half of
``pair_distance_m`` each; the robot gets the environment's contact distance minus that, so robot and pedestrian
keep exactly the environment's contact distance.

``pyrvo`` (Apache-2.0) is imported when the first crowd is made; RVO2 computes in single precision, so a
reacting pedestrian's velocity is exact to about 1e-7 relative.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.reaction.params import ReactionParams
from envs.reaction.steered import Neighbourhood, SteeredCrowd

#: Why ``pyrvo`` is needed, for the error raised without it.
PYRVO_MISSING = (
    "reaction='orca' needs the ORCA library binding pyrvo (Apache-2.0, Linux wheels with RVO2 inside): "
    "pip install pyrvo"
)


def _pyrvo() -> Any:
    try:
        import pyrvo
    except ImportError as exc:  # pragma: no cover - pyrvo is installed wherever orca runs
        raise ImportError(PYRVO_MISSING) from exc
    return pyrvo


class OrcaCrowd(SteeredCrowd):
    """``orca`` (see the module docstring and :mod:`envs.reaction.steered`)."""

    name = "orca"

    def __init__(self, params: ReactionParams, robot_radius_m: float, pedestrian_radius_m: float) -> None:
        super().__init__(params, robot_radius_m, pedestrian_radius_m)
        self._rvo = _pyrvo()
        self._ped_radius = params.pair_distance_m / 2.0
        self._robot_radius = self.contact_m - self._ped_radius

    def _model_velocities(self, hood: Neighbourhood) -> np.ndarray:
        prm = self.params
        # RVO2 cannot remove agents safely (its k-d tree keeps the removed ones), so a fresh simulator each step
        # (about a microsecond)
        sim = self._rvo.RVOSimulator()
        sim.set_time_step(hood.dt_s)
        nd, nn, th, r = prm.neighbor_distance_m, prm.orca_max_neighbors, prm.orca_time_horizon_s, self._ped_radius
        add = sim.add_agent
        # agents that move as they do: the robot and the non-reacting neighbours, seen by the reacting pedestrians. Of
        # another agent RVO2 reads only its position, velocity and radius (Agent::computeNewVelocity); these look at
        # nobody (no neighbours) and the velocity RVO2 computes for them is discarded, so their preferred velocity and
        # max speed are never read (left at 0).
        add(hood.robot.tolist(), 0.0, 0, th, th, self._robot_radius, 0.0, hood.robot_velocity.tolist())
        for pos, vel in zip(hood.other_positions.tolist(), hood.other_velocities.tolist(), strict=True):
            add(pos, 0.0, 0, th, th, r, 0.0, vel)
        vmax = prm.max_speed_mps
        ids = [
            add(pos, nd, nn, th, th, r, vmax, vel)
            for pos, vel in zip(hood.positions.tolist(), hood.velocities.tolist(), strict=True)
        ]
        prefer = sim.set_agent_pref_velocity
        for aid, pv in zip(ids, hood.preferred.tolist(), strict=True):
            prefer(aid, pv)
        sim.do_step()
        get = sim.get_agent_velocity
        return np.array([get(aid).to_tuple() for aid in ids], dtype=np.float64).reshape(-1, 2)
