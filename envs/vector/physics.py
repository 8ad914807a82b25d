"""Many worlds in one pymunk space: a robot disk per world and, per world, a pool of kinematic pedestrian disks.

The worlds share the space but never touch: a shape filter lets a robot collide with its own world's pedestrians
only. World ``w`` is ``(hi, lo) = divmod(w, 16)``; its robot has category bit ``hi`` and mask bit ``16 + lo``, its
pedestrians category bit ``16 + lo`` and mask bit ``hi``, so a pair passes the filter (which asks each shape's
categories to meet the other's mask) only when both halves agree: at most :data:`MAX_WORLDS` = 256 worlds, robots
never meet robots, pedestrians never meet pedestrians. Every world keeps its own coordinates (no offsets), so each
world's bodies, contacts and robot path are those of :class:`envs.world.World` alone in a space, bit for bit.

Each substep writes the position and velocity of every body in one :func:`pymunk.batch.set_space_bodies` call, steps
the space once, and reads every robot's position back with :func:`pymunk.batch.get_space_bodies`. As in
:class:`envs.world.World`, only pedestrians that can reach their robot during the control step get a body (a
pedestrian keeps its body while it stays near; a released body is reused from the next control step on); unused
bodies are parked far away, each at its own place. Contacts come from pymunk's collision callbacks (rare: a contact
ends the episode unless ``terminate_on_collision`` is off).
"""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np
import pymunk
import pymunk.batch

from envs.world import PEDESTRIAN_TYPE, ROBOT_TYPE, Contact, fault_of

#: Worlds one space can keep apart with the 32-bit shape filter (16 x 16).
MAX_WORLDS: Final[int] = 256
_PARK: Final[float] = 1.0e6
_FIELDS: Final[Any] = pymunk.batch.BodyFields.POSITION | pymunk.batch.BodyFields.VELOCITY


class BatchedWorld:
    """``num_worlds`` robot worlds in one pymunk space (see the module docstring).

    Args:
        num_worlds: W, at most :data:`MAX_WORLDS`.
        robot_radius_m: robot disk radius, metres.
        ped_radius_m: pedestrian disk radius, metres.

    Attributes:
        robot_positions: ``(W, 2)`` robot centres, metres (as pymunk has them).
    """

    def __init__(self, num_worlds: int, robot_radius_m: float, ped_radius_m: float) -> None:
        if not 1 <= num_worlds <= MAX_WORLDS:
            raise ValueError(
                f"num_envs must be in [1, {MAX_WORLDS}] (worlds one pymunk space keeps apart), got {num_worlds}"
            )
        self.num_worlds = num_worlds
        self.ped_radius_m = float(ped_radius_m)
        self.space = pymunk.Space()
        self.space.gravity = (0.0, 0.0)
        self._robots: list[pymunk.Body] = []
        self._shape_world: dict[int, int] = {}  # id(robot shape) -> world
        self._body_of_shape: dict[int, int] = {}  # id(pedestrian shape) -> pool index
        for w in range(num_worlds):
            body = pymunk.Body(1.0, math.inf)
            shape = pymunk.Circle(body, float(robot_radius_m))
            shape.collision_type = ROBOT_TYPE
            hi, lo = divmod(w, 16)
            shape.filter = pymunk.ShapeFilter(categories=1 << hi, mask=1 << (16 + lo))
            self.space.add(body, shape)
            self._robots.append(body)
            self._shape_world[id(shape)] = w
        self.robot_positions = np.zeros((num_worlds, 2))
        # the pedestrian pool: body k belongs to world _ped_world[k] and holds replay row _ped_row[k] (-1: parked)
        self._peds: list[pymunk.Body] = []
        self._ped_world = np.zeros(0, dtype=np.int64)
        self._ped_row = np.zeros(0, dtype=np.int64)
        self._free: list[list[int]] = [[] for _ in range(num_worlds)]
        self._pending: list[list[int]] = [[] for _ in range(num_worlds)]  # released: free from the next step on
        self.slot = np.full((num_worlds, 0), -1, dtype=np.int64)  # (W, P) pool index of each world's replay row
        # per world: rows in contact now -> fault; contacts begun in the current step
        self.touching: list[dict[int, str]] = [{} for _ in range(num_worlds)]
        self._touching_worlds: set[int] = set()
        self._events: dict[int, list[Contact]] = {}
        self._substep = 0
        self._robot_vel = np.zeros((num_worlds, 2))
        self._state = np.zeros((num_worlds, 4))  # every body's (x, y, vx, vy), in the space's body order
        self._park = np.zeros((0, 2))
        self._buffer = pymunk.batch.Buffer()
        self.space.on_collision(ROBOT_TYPE, PEDESTRIAN_TYPE, begin=self._begin, separate=self._separate)

    # ------------------------------------------------------------------ contacts

    def _begin(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        arbiter.process_collision = False  # report, never push
        robot_shape, ped_shape = arbiter.shapes
        if robot_shape.collision_type != ROBOT_TYPE:
            robot_shape, ped_shape = ped_shape, robot_shape
        k = self._body_of_shape[id(ped_shape)]
        row = int(self._ped_row[k])
        if row < 0:
            return
        w = self._shape_world[id(robot_shape)]
        pb, rb = ped_shape.body, robot_shape.body
        fault, r_app, p_app = fault_of(
            self._robot_vel[w].copy(),
            np.array([pb.velocity.x, pb.velocity.y]),
            np.array([rb.position.x, rb.position.y]),
            np.array([pb.position.x, pb.position.y]),
        )
        self.touching[w][row] = fault
        self._touching_worlds.add(w)
        self._events.setdefault(w, []).append(Contact(row, self._substep, fault, r_app, p_app))

    def _separate(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        robot_shape, ped_shape = arbiter.shapes
        if robot_shape.collision_type != ROBOT_TYPE:
            robot_shape, ped_shape = ped_shape, robot_shape
        k = self._body_of_shape.get(id(ped_shape))
        if k is None or self._ped_row[k] < 0:
            return
        w = self._shape_world[id(robot_shape)]
        self.touching[w].pop(int(self._ped_row[k]), None)
        if not self.touching[w]:
            self._touching_worlds.discard(w)

    # ------------------------------------------------------------------ lifecycle

    def reset_world(self, w: int, robot_position: np.ndarray, num_rows: int) -> None:
        """Start world ``w`` afresh: its robot at ``robot_position`` ``(2,)`` metres, every pedestrian body released
        (free from the next step on, so a body the robot touched is separated before reuse), no contacts;
        ``num_rows`` replay rows."""
        body = self._robots[w]
        body.position = (float(robot_position[0]), float(robot_position[1]))
        body.velocity = (0.0, 0.0)
        self.robot_positions[w] = (body.position.x, body.position.y)
        held = self.slot[w][self.slot[w] >= 0]
        self._ped_row[held] = -1
        self._pending[w].extend(held.tolist())
        self._ensure_rows(num_rows)
        self.slot[w] = -1
        self.touching[w] = {}
        self._touching_worlds.discard(w)

    def _ensure_rows(self, num_rows: int) -> None:
        if num_rows > self.slot.shape[1]:
            grown = np.full((self.num_worlds, max(num_rows, 2 * self.slot.shape[1])), -1, dtype=np.int64)
            grown[:, : self.slot.shape[1]] = self.slot
            self.slot = grown

    def _new_body(self, w: int) -> int:
        k = len(self._peds)
        body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        park = (_PARK + 10.0 * k, _PARK)
        body.position = park
        shape = pymunk.Circle(body, self.ped_radius_m)
        shape.collision_type = PEDESTRIAN_TYPE
        hi, lo = divmod(w, 16)
        shape.filter = pymunk.ShapeFilter(categories=1 << (16 + lo), mask=1 << hi)
        self.space.add(body, shape)
        self._peds.append(body)
        self._body_of_shape[id(shape)] = k
        self._ped_world = np.append(self._ped_world, w)
        self._ped_row = np.append(self._ped_row, -1)
        self._park = np.vstack([self._park, park])
        return k

    def _assign(self, near: np.ndarray) -> None:
        """Give every near ``(W, P)`` row a body (keeping those it has), release the others' bodies."""
        held = self.slot >= 0
        changed = np.flatnonzero((near != held).any(axis=1))
        grew = False
        for w in changed.tolist():
            slot_w = self.slot[w]
            released = slot_w[held[w] & ~near[w]]
            if len(released):
                rows = self._ped_row[released]
                self._ped_row[released] = -1
                for row in rows.tolist():
                    self.touching[w].pop(row, None)
                if not self.touching[w]:
                    self._touching_worlds.discard(w)
                slot_w[held[w] & ~near[w]] = -1
            for row in np.flatnonzero(near[w] & ~held[w]).tolist():
                if self._free[w]:
                    k = self._free[w].pop()
                else:
                    k = self._new_body(w)
                    grew = True
                slot_w[row] = k
                self._ped_row[k] = row
            self._pending[w].extend(released.tolist())
        if grew:
            self._state = np.zeros((self.num_worlds + len(self._peds), 4))

    def end_step(self) -> None:
        """Bodies released during the step become free for the next one."""
        for w in range(self.num_worlds):
            if self._pending[w]:
                self._free[w].extend(self._pending[w])
                self._pending[w] = []

    # ------------------------------------------------------------------ stepping

    def step(
        self,
        robot_velocities: np.ndarray,
        ped_positions: np.ndarray,
        ped_present: np.ndarray,
        near: np.ndarray,
        substep_s: float,
    ) -> tuple[np.ndarray, dict[int, list[Contact]], dict[int, frozenset[int]]]:
        """Advance every world by one control step of ``S`` substeps.

        Args:
            robot_velocities: ``(W, S, 2)`` commanded robot velocity in each substep, m/s (0 for a world standing
                still this step).
            ped_positions: ``(W, S + 1, P, 2)`` replay positions at the substep boundaries, metres (P >= every
                world's rows; only near rows are read).
            ped_present: ``(W, S + 1, P)`` presence at the boundaries (pop-in ghosts already removed).
            near: ``(W, P)`` rows that may touch their robot during the step (they get bodies).
            substep_s: substep length, seconds.

        Returns:
            ``(robot_path (W, S + 1, 2), contacts, touched)``: robot centres at the substep boundaries; per world
            with any, the contacts begun in the step ordered by (substep, row) and the rows in contact at the end
            of any substep (worlds with neither are absent).
        """
        num_w, num_sub = robot_velocities.shape[:2]
        self._ensure_rows(near.shape[1])
        if near.shape[1] < self.slot.shape[1]:
            wide = np.zeros(self.slot.shape, dtype=bool)
            wide[:, : near.shape[1]] = near
            near = wide
        self._assign(near)
        self._events = {}
        path = np.empty((num_w, num_sub + 1, 2))
        path[:, 0] = self.robot_positions
        wi, rows = np.nonzero(self.slot >= 0)
        k_of = self.slot[wi, rows]
        p = ped_positions[wi, :, rows] if len(wi) else np.zeros((0, num_sub + 1, 2))  # (M, S + 1, 2)
        on = ped_present[wi, :, rows] if len(wi) else np.zeros((0, num_sub + 1), dtype=bool)
        inv_h = 1.0 / substep_s
        nw = self.num_worlds
        state = self._state
        state[nw:, 0:2] = self._park
        state[nw:, 2:4] = 0.0
        touched: dict[int, set[int]] = {}
        for k in range(num_sub):
            self._substep = k
            state[:nw, 0:2] = self.robot_positions
            state[:nw, 2:4] = robot_velocities[:, k]
            self._robot_vel = robot_velocities[:, k]
            if len(k_of):
                both = on[:, k] & on[:, k + 1]
                appear = ~on[:, k] & on[:, k + 1]
                x0, x1 = p[:, k], p[:, k + 1]
                pos = np.where(both[:, None], x0, np.where(appear[:, None], x1, self._park[k_of]))
                vel = np.where(both[:, None], (x1 - x0) * inv_h, 0.0)
                state[nw + k_of, 0:2] = pos
                state[nw + k_of, 2:4] = vel
            buf = self._buffer
            buf.clear()
            buf.set_float_buf(state.tobytes())
            pymunk.batch.set_space_bodies(self.space, _FIELDS, buf)
            self.space.step(substep_s)
            buf.clear()
            pymunk.batch.get_space_bodies(self.space, pymunk.batch.BodyFields.POSITION, buf)
            self.robot_positions = np.frombuffer(buf.float_buf(), dtype=np.float64, count=2 * nw).reshape(nw, 2).copy()
            path[:, k + 1] = self.robot_positions
            for w in self._touching_worlds:
                touched.setdefault(w, set()).update(self.touching[w])
        contacts = {w: sorted(ev, key=lambda c: (c.substep, c.row)) for w, ev in self._events.items()}
        return path, contacts, {w: frozenset(rows_w) for w, rows_w in touched.items()}
