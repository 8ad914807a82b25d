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

import math
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
        nd, nn, th = prm.neighbor_distance_m, prm.orca_max_neighbors, prm.orca_time_horizon_s
        add, prefer = sim.add_agent, sim.set_agent_pref_velocity
        # agents that move as they do: the robot and the non-reacting neighbours. They look at nobody (no neighbours:
        # RVO2 would compute velocities for them that are discarded), keep their velocity (max speed = its norm) and
        # are seen by the reacting pedestrians.
        rx, ry = hood.robot.tolist()
        rv = tuple(hood.robot_velocity.tolist())
        prefer(add((rx, ry), 0.0, 0, th, th, self._robot_radius, _speed(rv), rv), rv)
        for pos, vel in zip(hood.other_positions.tolist(), hood.other_velocities.tolist(), strict=True):
            v = (vel[0], vel[1])
            prefer(add((pos[0], pos[1]), 0.0, 0, th, th, self._ped_radius, _speed(v), v), v)
        ids = []
        vmax = prm.max_speed_mps
        for pos, vel, pv in zip(
            hood.positions.tolist(), hood.velocities.tolist(), hood.preferred.tolist(), strict=True
        ):
            aid = add((pos[0], pos[1]), nd, nn, th, th, self._ped_radius, vmax, (vel[0], vel[1]))
            prefer(aid, (pv[0], pv[1]))
            ids.append(aid)
        sim.do_step()
        get = sim.get_agent_velocity
        out = []
        for aid in ids:
            v = get(aid)
            out.append((v.x, v.y))
        return np.array(out, dtype=np.float64).reshape(-1, 2)


def _speed(v: tuple[float, float]) -> float:
    """An agent's max speed for a velocity it keeps (a hair above its norm, so RVO2 does not shorten it)."""
    return math.hypot(v[0], v[1]) * (1.0 + 1e-6) + 1e-9
