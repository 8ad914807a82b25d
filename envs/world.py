"""The pymunk world: a dynamic robot disk and kinematic pedestrian disks, in metres and seconds.

Only pedestrians that can reach the robot during a control step are put into the space: a pool of
kinematic bodies is assigned to them (a pedestrian keeps its body while it stays near); unused bodies
are parked far away. Every physics substep, each pedestrian body is placed at its replay position and
given the velocity that carries it to its next replay position, so contacts see the true relative
speed. Contacts are reported by pymunk's collision callbacks and do not push anyone (replayed
pedestrians ignore the robot; the robot's velocity is commanded).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
import pymunk

ROBOT_TYPE: Final[int] = 1
PEDESTRIAN_TYPE: Final[int] = 2
_PARK_X: Final[float] = 1.0e6


@dataclass(frozen=True)
class Contact:
    """A robot-pedestrian contact that began during a substep.

    Attributes:
        row: the pedestrian's replay row.
        substep: index of the substep (0-based) in the control step.
        fault: ``"robot"`` if the robot's speed towards the pedestrian exceeded the pedestrian's
            speed towards the robot at contact, else ``"pedestrian"``.
        robot_approach_mps: robot velocity along the line to the pedestrian, m/s.
        pedestrian_approach_mps: pedestrian velocity along the line to the robot, m/s.
    """

    row: int
    substep: int
    fault: str
    robot_approach_mps: float
    pedestrian_approach_mps: float


@dataclass
class WorldStep:
    """What happened during one control step.

    Attributes:
        robot_positions: ``(S + 1, 2)`` robot centre at the substep boundaries, metres.
        contacts: contacts that began during the step, by substep, then replay row.
        touching: replay rows in contact at the end of any substep of the step.
    """

    robot_positions: np.ndarray
    contacts: list[Contact] = field(default_factory=list)
    touching: frozenset[int] = frozenset()


def fault_of(
    robot_vel: np.ndarray, ped_vel: np.ndarray, robot_pos: np.ndarray, ped_pos: np.ndarray
) -> tuple[str, float, float]:
    """Who was at fault in a contact: the side moving faster towards the other (ties: the pedestrian).

    Returns:
        ``(fault, robot_approach_mps, pedestrian_approach_mps)``.
    """
    d = np.asarray(ped_pos, dtype=np.float64) - np.asarray(robot_pos, dtype=np.float64)
    norm = float(np.hypot(d[0], d[1]))
    n = d / norm if norm > 1e-9 else np.zeros(2)
    robot_app = float(np.dot(robot_vel, n))
    ped_app = float(-np.dot(ped_vel, n))
    return ("robot" if robot_app > ped_app else "pedestrian"), robot_app, ped_app


def robot_path(start: np.ndarray, velocities: Sequence[tuple[float, float]], substep_s: float) -> np.ndarray:
    """``(S + 1, 2)`` the robot's centre at the substep ends of a control step commanding ``velocities`` (``S`` pairs,
    m/s) from ``start`` (metres), integrated as pymunk moves the robot (``p += v * h`` per substep; nothing pushes
    it), so the same floats as :attr:`WorldStep.robot_positions`."""
    path = np.empty((len(velocities) + 1, 2))
    x, y = float(start[0]), float(start[1])
    path[0] = x, y
    for k, (vx, vy) in enumerate(velocities):
        x, y = x + vx * substep_s, y + vy * substep_s
        path[k + 1] = x, y
    return path


class World:
    """The pymunk space.

    Args:
        robot_radius_m: robot disk radius, metres.
        ped_radius_m: pedestrian disk radius, metres.
    """

    def __init__(self, robot_radius_m: float, ped_radius_m: float) -> None:
        self.robot_radius_m = float(robot_radius_m)
        self.ped_radius_m = float(ped_radius_m)
        self.reset(np.zeros(2))

    # ------------------------------------------------------------------ lifecycle

    def reset(self, robot_position: np.ndarray) -> None:
        """A fresh space with the robot at ``robot_position`` (metres) and no pedestrian bodies."""
        self.space = pymunk.Space()
        self.space.gravity = (0.0, 0.0)
        self.robot = pymunk.Body(1.0, math.inf)
        self.robot.position = (float(robot_position[0]), float(robot_position[1]))
        shape = pymunk.Circle(self.robot, self.robot_radius_m)
        shape.collision_type = ROBOT_TYPE
        self.space.add(self.robot, shape)
        self._slots: list[tuple[pymunk.Body, pymunk.Circle]] = []
        self._free: list[int] = []
        self._slot_of: dict[int, int] = {}
        self._row_of_shape: dict[int, int] = {}
        self._touching: dict[int, str] = {}
        self._events: list[Contact] = []
        self._substep = 0
        self._robot_vel = (0.0, 0.0)
        self.space.on_collision(ROBOT_TYPE, PEDESTRIAN_TYPE, begin=self._begin, separate=self._separate)

    @property
    def robot_position(self) -> np.ndarray:
        p = self.robot.position
        return np.array([p.x, p.y])

    @property
    def num_bodies(self) -> int:
        """Pedestrian bodies in the pool (for tests and benchmarks)."""
        return len(self._slots)

    # ------------------------------------------------------------------ contacts

    def _begin(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        arbiter.process_collision = False  # report, never push
        robot_shape, ped_shape = arbiter.shapes
        if robot_shape.collision_type != ROBOT_TYPE:
            robot_shape, ped_shape = ped_shape, robot_shape
        row = self._row_of_shape.get(id(ped_shape))
        if row is None:
            return
        pb = ped_shape.body
        fault, r_app, p_app = fault_of(
            np.array(self._robot_vel),
            np.array([pb.velocity.x, pb.velocity.y]),
            self.robot_position,
            np.array([pb.position.x, pb.position.y]),
        )
        self._touching[row] = fault
        self._events.append(Contact(row, self._substep, fault, r_app, p_app))

    def _separate(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        shapes = arbiter.shapes
        for shape in shapes:
            row = self._row_of_shape.get(id(shape))
            if row is not None:
                self._touching.pop(row, None)

    # ------------------------------------------------------------------ pool

    def _assign(self, rows: np.ndarray) -> list[tuple[int, pymunk.Body]]:
        wanted = set(rows.tolist())
        released = []
        for row in [r for r in self._slot_of if r not in wanted]:
            slot = self._slot_of.pop(row)
            body, shape = self._slots[slot]
            body.position = (_PARK_X + 10.0 * slot, _PARK_X)
            body.velocity = (0.0, 0.0)
            self._row_of_shape.pop(id(shape), None)
            self._touching.pop(row, None)
            released.append(slot)
        out = []
        for row in rows.tolist():
            slot = self._slot_of.get(row)
            if slot is None:
                if self._free:
                    slot = self._free.pop()
                else:
                    slot = len(self._slots)
                    body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
                    body.position = (_PARK_X + 10.0 * slot, _PARK_X)
                    shape = pymunk.Circle(body, self.ped_radius_m)
                    shape.collision_type = PEDESTRIAN_TYPE
                    self.space.add(body, shape)
                    self._slots.append((body, shape))
                self._slot_of[row] = slot
                self._row_of_shape[id(self._slots[slot][1])] = row
            out.append((row, self._slots[slot][0]))
        # A released body is reused only from the next control step on, after pymunk has separated it.
        self._free.extend(released)
        return out

    # ------------------------------------------------------------------ stepping

    def step(
        self,
        robot_velocities: Sequence[tuple[float, float]],
        ped_positions: np.ndarray,
        ped_present: np.ndarray,
        rows: np.ndarray,
        substep_s: float,
    ) -> WorldStep:
        """Advance one control step of ``S`` substeps.

        Args:
            robot_velocities: ``S`` pairs: commanded robot velocity (x, y) in each substep, m/s.
            ped_positions: ``(S + 1, n, 2)`` replay positions of the pedestrians in ``rows`` at the
                substep boundaries, metres.
            ped_present: ``(S + 1, n)`` bool presence at the boundaries.
            rows: ``(n,)`` replay rows of the pedestrians that may touch the robot in this step.
            substep_s: substep length, seconds.
        """
        num_sub = len(robot_velocities)
        bodies = self._assign(rows)
        self._events = []
        robot_path = np.empty((num_sub + 1, 2))
        robot_path[0] = self.robot_position
        pos_list = ped_positions.tolist()
        pres_list = ped_present.tolist()
        inv_h = 1.0 / substep_s
        touched: set[int] = set()
        for k in range(num_sub):
            self._substep = k
            p_now, p_next = pos_list[k], pos_list[k + 1]
            on_now, on_next = pres_list[k], pres_list[k + 1]
            for j, (row, body) in enumerate(bodies):
                if on_now[j] and on_next[j]:
                    x0, y0 = p_now[j]
                    x1, y1 = p_next[j]
                    body.position = (x0, y0)
                    body.velocity = ((x1 - x0) * inv_h, (y1 - y0) * inv_h)
                elif on_next[j]:  # appears during the substep
                    body.position = tuple(p_next[j])
                    body.velocity = (0.0, 0.0)
                else:  # absent, or leaves during the substep
                    body.position = (_PARK_X + 10.0 * self._slot_of[row], _PARK_X)
                    body.velocity = (0.0, 0.0)
            vx, vy = robot_velocities[k]
            self._robot_vel = (vx, vy)
            self.robot.velocity = (vx, vy)
            self.space.step(substep_s)
            if self._touching:
                touched.update(self._touching)
            p = self.robot.position
            robot_path[k + 1] = (p.x, p.y)
        # contacts in (substep, row) order: pymunk reports the contacts of one substep in its broad phase's order
        events = sorted(self._events, key=lambda c: (c.substep, c.row))
        return WorldStep(robot_path, events, frozenset(touched))
