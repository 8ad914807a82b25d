"""The privileged ceiling: a planner that reads the replay's true future of every pedestrian (PRIVILEGED).

No policy ever has this information: it is the measuring stick of what is attainable on an episode, and a
possible teacher, never a competitor. It reads the environment itself (its replay, robot, goal, clock), never
the observation, and is labelled ``privileged`` in every output (``"privileged": true`` in evaluation summaries).

Usage: ``PrivilegedPlanner(cfg).bind_envs([env, ...])`` before each batched ``predict`` (one environment per
row; :func:`agents.rollout.run_episodes` does it for every policy with a ``bind_envs`` method), or
``PrivilegedPlanner(cfg, env=env)`` for one environment.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from agents.planners.base import _fractions_and_headings, _Planner
from agents.planners.search import SEARCH_HEADINGS_DEG, SEARCH_SPEED_FRACTIONS, lattice_select, motion_candidates
from envs.config import CrowdNavConfig

#: Parents expanded at once (bounds memory when the search runs without a cap on states).
_CHUNK: Final[int] = 4000
#: A robot this close (metres) to where its plan put it is on the plan.
_ON_PLAN_M: Final[float] = 1e-6


def command_velocities(velocity: np.ndarray, speed_mps: float) -> tuple[np.ndarray, np.ndarray]:
    """The float32 actions ``(..., 2)`` of holonomic motions at velocities ``(..., 2)`` m/s, and the velocities the
    environment commands for them (scaled by the preferred speed ``speed_mps``, norm capped at it, as ``env.step``
    does; the norm with numpy's ``hypot``, which can differ from the environment's :func:`math.hypot` in the last bit:
    :func:`agents.planners.privileged_reactive.env_velocities` gives the environment's floats exactly)."""
    action = np.clip(velocity / speed_mps, -1.0, 1.0).astype(np.float32)
    cmd = action.astype(np.float64) * speed_mps
    speed = np.hypot(cmd[..., 0], cmd[..., 1])
    over = speed > speed_mps
    cmd = np.where(over[..., None], cmd * (speed_mps / np.where(over, speed, 1.0))[..., None], cmd)
    return action, cmd


@dataclass
class Plan:
    """A plan from step ``start_step`` of an episode.

    Attributes:
        episode: the episode object it was made for (``env.episode``).
        start_step: the control step it starts at.
        actions: ``(L, 2)`` float32 actions, one per control step.
        positions: ``(L + 1, 2)`` robot centre at the step boundaries (exactly as the world integrates), metres.
        reaches_goal: it ends on the goal without contact (False: the longest contact-free prefix found).
        capped: found with the cap on states per layer (False: without it, or not found).
        seconds: time spent searching.
    """

    episode: Any
    start_step: int
    actions: np.ndarray
    positions: np.ndarray
    reaches_goal: bool
    capped: bool
    seconds: float = 0.0


@dataclass
class PlannerStats:
    """Counts over the plans made (for reports and tests)."""

    plans: int = 0
    found: int = 0
    uncapped: int = 0
    seconds: float = 0.0
    failures: list[tuple[str, float]] = field(default_factory=list)


class BoundPlanner(_Planner):
    """What the privileged planners share: they read their environments, bound row by row before each ``predict``,
    never the observation (which only gives the batch size). A subclass implements ``_action(env) -> (2,)`` float32
    and may refuse an environment in ``_check_env(config)``."""

    privileged: Final[bool] = True
    #: The planner as error messages name it.
    label: str = "the privileged planner"

    _envs: list[Any]

    def _check_env(self, config: CrowdNavConfig) -> None:  # pragma: no cover - default: every environment
        pass

    def _action(self, env: Any) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def bind_envs(self, envs: Sequence[Any]) -> None:
        """The environments of the rows of the next ``predict`` (row ``i`` is ``envs[i]``; wrappers are unwrapped)."""
        unwrapped = [getattr(e, "unwrapped", e) for e in envs]
        for e in unwrapped:
            self._check_env(e.config)
        self._envs = unwrapped

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Actions ``(B, 2)`` float32 for the bound environments' current states (the batched observation only gives
        ``B``: the planner never reads it)."""
        b = len(obs["mask"])
        if len(self._envs) != b:
            raise ValueError(
                f"{self.label} is bound to {len(self._envs)} environment(s) but got {b} observation(s): "
                "call bind_envs(envs) with one environment per row first"
            )
        return np.stack([self._action(env) for env in self._envs])


class PrivilegedPlanner(BoundPlanner):
    """PRIVILEGED: searches the rest of the episode for the fastest contact-free route, knowing every pedestrian's
    true future.

    Layers of one control step: every state is expanded by :func:`agents.planners.search.motion_candidates` (16
    headings around the full circle x 3 speeds, 3 goal-directed speeds — the fastest arriving exactly —, standing: 52
    velocities), each velocity as the environment will command it (the float32 action, scaled and capped as
    ``env.step`` does). The robot's path is integrated per physics substep as the world does, and checked
    against every pedestrian of the replay at the substep ends (``replay.positions_at`` at
    ``env.substep_times``), where contacts happen, with ``margin_m`` to spare. Children are de-duplicated on a
    ``cell_m`` lattice and the ``max_states`` nearest the goal are kept; if that finds no route, the search is
    repeated without the cap. The first layer with a child on the goal gives the plan, followed step by step
    (replanned if the robot is ever off it).

    It treats every pedestrian as solid from its first annotation, which is at least as strict as the
    environment's pop-in rule (:mod:`envs.popin`: a track beginning on the robot is a contact-less ghost), so
    its plans never meet a pop-in. Holonomic kinematics only.

    Args:
        env_config: the environment's configuration.
        env: an environment to bind at once (single-environment use).
        cell_m: lattice of the de-duplication, metres.
        max_states: states kept per layer in the first pass.
        margin_m: gap kept beyond touching at the substep ends, metres.
        headings_deg: headings relative to the goal direction, degrees.
        speed_fractions: speeds as fractions of the preferred speed.
    """

    def __init__(
        self,
        env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
        env: Any = None,
        cell_m: float = 0.1,
        max_states: int = 3000,
        margin_m: float = 0.01,
        headings_deg: Sequence[float] = SEARCH_HEADINGS_DEG,
        speed_fractions: Sequence[float] = SEARCH_SPEED_FRACTIONS,
    ) -> None:
        super().__init__(env_config if env_config is not None or env is None else env.unwrapped.config)
        if self.cfg.kinematics != "holonomic":
            raise ValueError(
                f"the privileged planner plans holonomic motions; kinematics {self.cfg.kinematics!r} is not supported"
            )
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell_m must be a finite number > 0, got {cell_m!r}")
        if max_states < 1:
            raise ValueError(f"max_states must be >= 1, got {max_states!r}")
        if not (math.isfinite(margin_m) and margin_m >= 0):
            raise ValueError(f"margin_m must be a finite number >= 0, got {margin_m!r}")
        self.headings, self.fractions = _fractions_and_headings(headings_deg, speed_fractions)
        self.cell_m = float(cell_m)
        self.max_states = int(max_states)
        self.contact_m = self.cfg.robot_radius_m + self.cfg.pedestrian_radius_m + float(margin_m)
        self.stats = PlannerStats()
        self._envs: list[Any] = []
        self._plans: dict[int, Plan] = {}
        if env is not None:
            self.bind_envs([env])

    # ------------------------------------------------------------------ the SB3 interface

    def _check_env(self, config: CrowdNavConfig) -> None:
        if config.kinematics != "holonomic":
            raise ValueError("the privileged planner plans holonomic motions; the environment is unicycle")

    def _action(self, env: Any) -> np.ndarray:
        plan = self._plans.get(id(env))
        k = -1
        if plan is not None and plan.episode is env.episode:
            k = env.steps_taken - plan.start_step
            if k >= len(plan.actions) or np.abs(env.robot_position - plan.positions[max(k, 0)]).max() > _ON_PLAN_M:
                k = -1
        if plan is None or k < 0:
            plan = self.plan(env)
            self._plans[id(env)] = plan
            k = 0
        if len(plan.actions) == 0:  # nothing is contact-free: stand (the episode is lost either way)
            return np.zeros(2, dtype=np.float32)
        return plan.actions[k].copy()

    # ------------------------------------------------------------------ planning

    def command(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The float32 actions ``(..., 2)`` for velocities ``(..., 2)`` m/s, and the velocities the environment
        commands for them (:func:`command_velocities`)."""
        return command_velocities(velocity, self.cfg.robot_pref_speed_mps)

    def plan(self, env: Any) -> Plan:
        """The fastest contact-free route from the environment's current state to its goal (see the class doc)."""
        started = time.perf_counter()
        env = getattr(env, "unwrapped", env)
        ep = env.episode
        if ep is None:
            raise RuntimeError("the environment has no episode: call reset() first")
        n0 = env.steps_taken
        steps = ep.max_steps - n0
        robot = env.robot_position
        if steps <= 0:
            return Plan(ep, n0, np.zeros((0, 2), dtype=np.float32), robot[None], False, False)
        times = np.stack([env.substep_times(n0 + j)[1:] for j in range(steps)])
        peds, present = env.replay.positions_at(times.reshape(-1))
        s = times.shape[1]
        peds = peds.reshape(steps, s, -1, 2)
        present = present.reshape(steps, s, -1)
        found = self._search(robot, ep.goal, peds, present, self.max_states)
        capped = found[2]
        if not capped:
            self.stats.uncapped += 1
            found = self._search(robot, ep.goal, peds, present, None)
        actions, positions, reached = found
        self.stats.plans += 1
        self.stats.found += int(reached)
        seconds = time.perf_counter() - started
        self.stats.seconds += seconds
        if not reached:
            self.stats.failures.append((ep.recording.name, float(ep.t0_s)))
        return Plan(ep, n0, actions, positions, reached, capped and reached, seconds)

    def _search(
        self, robot: np.ndarray, goal: np.ndarray, peds: np.ndarray, present: np.ndarray, keep: int | None
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """Layered search; ``peds`` ``(L, S, N, 2)`` and ``present`` ``(L, S, N)`` at the substep ends of the remaining
        steps. Returns ``(actions (J, 2), positions (J + 1, 2), reaches_goal)``."""
        cfg = self.cfg
        dt, v = cfg.dt_s, cfg.robot_pref_speed_mps
        h = dt / peds.shape[1]
        tol = cfg.goal_tolerance_m - 1e-9
        goal = np.asarray(goal, dtype=np.float64)
        base = math.atan2(goal[1] - robot[1], goal[0] - robot[0])
        x = np.asarray(robot, dtype=np.float64)[None]  # (M, 2)
        layers: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (parent, action, position) per layer
        for j in range(len(peds)):
            parent, action, child, arrived = self._expand(x, goal, base, peds[j], present[j], v, dt, h, tol)
            if arrived >= 0:
                layers.append(
                    (parent[arrived : arrived + 1], action[arrived : arrived + 1], child[arrived : arrived + 1])
                )
                return (*self._backtrack(robot, layers, 0), True)
            if len(child) == 0:
                break
            to_goal = np.hypot(goal[0] - child[:, 0], goal[1] - child[:, 1])
            # one child per cell (the nearest the goal, to the centimetre), then the nearest the goal
            level = np.rint(to_goal * 100.0)
            kept = lattice_select(np.zeros(len(child), dtype=np.int64), child, level, to_goal, self.cell_m, keep)
            layers.append((parent[kept], action[kept], child[kept]))
            x = child[kept]
        if not layers:
            return np.zeros((0, 2), dtype=np.float32), np.asarray(robot, dtype=np.float64)[None], False
        last = layers[-1][2]
        best = int(np.argmin(np.hypot(goal[0] - last[:, 0], goal[1] - last[:, 1])))
        return (*self._backtrack(robot, layers, best), False)

    def _expand(
        self,
        x: np.ndarray,
        goal: np.ndarray,
        base: float,
        peds: np.ndarray,
        present: np.ndarray,
        v: float,
        dt: float,
        h: float,
        tol: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Contact-free children of states ``x`` ``(M, 2)`` over one step (pedestrians ``(S, N, 2)`` at its substep
        ends): ``(parent (C,), action (C, 2) float32, position (C, 2), index of a child on the goal or -1)``."""
        parents, actions, children = [], [], []
        for lo in range(0, len(x), _CHUNK):
            xs = x[lo : lo + _CHUNK]
            action, cmd = self.command(motion_candidates(xs, goal, base, v, dt, self.headings, self.fractions))
            path = np.empty((peds.shape[0], *cmd.shape))  # (S, M, A, 2), integrated per substep as the world does
            pos = np.broadcast_to(xs[:, None, :], cmd.shape)
            for k in range(peds.shape[0]):
                pos = pos + cmd * h
                path[k] = pos
            ok = ~self._contacts(xs, path, peds, present, v * dt)
            m, a = np.nonzero(ok)
            end = path[-1, m, a]
            hit = np.flatnonzero(np.hypot(goal[0] - end[:, 0], goal[1] - end[:, 1]) <= tol)
            if len(hit):
                i = int(hit[0])
                return np.array([lo + m[i]]), action[m[i], a[i]][None], end[i : i + 1], 0
            parents.append(lo + m)
            actions.append(action[m, a])
            children.append(end)
        return np.concatenate(parents), np.concatenate(actions), np.concatenate(children), -1

    def _contacts(
        self, x: np.ndarray, path: np.ndarray, peds: np.ndarray, present: np.ndarray, reach_m: float
    ) -> np.ndarray:
        """``(M, A)`` bool: the motion comes within ``contact_m`` of a present pedestrian at a substep end."""
        _, m, a, _ = path.shape
        hit = np.zeros((m, a), dtype=bool)
        if not present.any():
            return hit
        lo, hi = x.min(axis=0) - reach_m - self.contact_m, x.max(axis=0) + reach_m + self.contact_m
        inside = present & np.all((peds >= lo) & (peds <= hi), axis=-1)  # (S, N)
        cols = np.flatnonzero(inside.any(axis=0))
        if len(cols) == 0:
            return hit
        q, qp = peds[:, cols], inside[:, cols]  # (S, P, 2), (S, P)
        d = np.hypot(x[None, :, None, 0] - q[:, None, :, 0], x[None, :, None, 1] - q[:, None, :, 1])  # (S, M, P)
        near = (np.where(qp[:, None, :], d, np.inf) < reach_m + self.contact_m).any(axis=0)  # (M, P)
        mi, pi = np.nonzero(near)
        if len(mi) == 0:
            return hit
        dx = path[..., 0][:, mi] - q[..., 0][:, pi, None]  # (S, n, A)
        dy = path[..., 1][:, mi] - q[..., 1][:, pi, None]
        close = (np.hypot(dx, dy) < self.contact_m) & qp[:, pi, None]
        pair_hit = close.any(axis=0)  # (n, A)
        starts = np.flatnonzero(np.r_[True, mi[1:] != mi[:-1]])
        hit[mi[starts]] = np.logical_or.reduceat(pair_hit, starts, axis=0)
        return hit

    def _backtrack(
        self, robot: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray, np.ndarray]], index: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Actions ``(J, 2)`` and positions ``(J + 1, 2)`` of the route ending at entry ``index`` of the last layer."""
        actions, positions = [], []
        for parent, action, child in reversed(layers):
            actions.append(action[index])
            positions.append(child[index])
            index = int(parent[index])
        positions.append(np.asarray(robot, dtype=np.float64))
        return np.stack(actions[::-1]), np.stack(positions[::-1])
