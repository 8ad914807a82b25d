"""The privileged reactive ceiling: a planner that rolls the environment's reaction model forward for its candidate
plans (PRIVILEGED).

Among pedestrians who react to the robot (``reaction`` ``pause``, ``orca`` or ``social_force``; ``docs/reaction.md``)
the recorded future is not what happens: people answer the robot's motion. The replay ceiling
(:class:`agents.planners.privileged.PrivilegedPlanner`) plans against the recording and is no ceiling there. This
planner plans against what the pedestrians would do in reply: it reads the environment's reaction model through
:meth:`envs.crowd_nav.CrowdNavEnv.reaction_snapshot` and scores every candidate motion on the crowd that motion
produces (:meth:`envs.reactive.ReactionSnapshot.simulate`, the environment's own rules, bit for bit). No policy has
this information: like the replay ceiling it is a measuring stick (is a failure avoidable at all?), never a
competitor, it reads the environment itself and never the observation, and it is labelled ``privileged`` in every
output.

Usage: ``make_planner("privileged", cfg, reactive=True)`` (or :class:`ReactivePrivilegedPlanner` directly), then
``bind_envs([env, ...])`` before each batched ``predict`` (:func:`agents.rollout.run_episodes` does it), or
``ReactivePrivilegedPlanner(cfg, env=env)`` for one environment.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from agents.planners.base import _fractions_and_headings
from agents.planners.privileged import BoundPlanner, command_velocities
from agents.planners.search import SEARCH_HEADINGS_DEG, SEARCH_SPEED_FRACTIONS, motion_candidates
from envs.config import CrowdNavConfig

#: Roll-outs tried per kept state in a layer (beyond the first layer, which may try every candidate): bounds the cost
#: of a layer in which most motions end in contact.
_TRIES_PER_STATE: Final[int] = 4

#: The planner's options (:func:`agents.planners.make_planner` names them when one is unknown).
REACTIVE_OPTIONS: Final[tuple[str, ...]] = (
    "beam",
    "wide_beam",
    "horizon_steps",
    "replan_steps",
    "cell_m",
    "margin_m",
    "headings_deg",
    "speed_fractions",
)


def env_velocities(actions: np.ndarray, speed_mps: float) -> np.ndarray:
    """The velocities ``(..., 2)`` m/s the holonomic ``env.step`` commands for float32 ``actions`` ``(..., 2)`` in
    ``[-1, 1]``: the action times the preferred speed ``speed_mps``, its norm capped at it, in the environment's floats
    exactly (the norm with :func:`math.hypot`, as the environment takes it: numpy's ``hypot``, which
    :func:`agents.planners.privileged.command_velocities` uses, can differ in the last bit, and a reaction model carries
    such a difference on into the crowd)."""
    out = np.asarray(actions, dtype=np.float64) * speed_mps
    flat = out.reshape(-1, 2)
    # only an action of norm 1 or more can be capped; numpy's norm is within an ulp of math.hypot's
    for i in np.flatnonzero(np.hypot(flat[:, 0], flat[:, 1]) > speed_mps * (1.0 - 1e-9)).tolist():
        vx, vy = float(flat[i, 0]), float(flat[i, 1])
        norm = math.hypot(vx, vy)
        if norm > speed_mps:
            flat[i] = vx * (speed_mps / norm), vy * (speed_mps / norm)
    return flat.reshape(out.shape)


@dataclass
class ReactivePlan:
    """A plan from step ``start_step`` of an episode, with the crowd it produces.

    Attributes:
        episode: the episode object it was made for (``env.episode``).
        start_step: the control step it starts at.
        actions: ``(L, 2)`` float32 actions, one per control step.
        positions: ``(L + 1, 2)`` the robot's centre at the step boundaries (as the world integrates), metres.
        crowd: ``(L, N, 2)`` the pedestrians at the end of each step (replay rows; meaningless where absent), metres.
        present: ``(L, N)`` bool there (pop-in ghosts absent), as ``env.pedestrians`` reports them.
        reaches_goal: the last step ends on the goal.
        widened: made by the second search, with ``wide_beam`` (the first did not reach the goal).
        contact_free: every step keeps clear of every present pedestrian at every substep end by the margin (False
            only for the one-step escape taken when no first motion is clear).
        simulations: roll-outs of one control step the search made.
        seconds: time spent searching.
    """

    episode: Any
    start_step: int
    actions: np.ndarray
    positions: np.ndarray
    crowd: np.ndarray
    present: np.ndarray
    reaches_goal: bool
    contact_free: bool
    widened: bool = False
    simulations: int = 0
    seconds: float = 0.0


@dataclass
class ReactivePlannerStats:
    """Counts over the plans made (for reports and tests)."""

    plans: int = 0
    """Searches made (one per plan, both passes counted once)."""
    found: int = 0
    """Plans that reach the goal."""
    widened: int = 0
    """Plans made by the second search, with ``wide_beam``."""
    escapes: int = 0
    """Escapes: no first motion was clear."""
    simulations: int = 0
    """Roll-outs of one control step."""
    seconds: float = 0.0
    """Time spent searching."""


@dataclass
class _Layer:
    """The states kept after one control step: their parent (index in the layer before), the action that reached them,
    where the robot and the crowd are, and the crowd to roll on from (dropped once the next layer exists)."""

    parent: list[int]
    action: list[np.ndarray]
    robot: list[np.ndarray]
    crowd: list[np.ndarray]
    present: list[np.ndarray]
    velocity: list[np.ndarray]
    ends: list[Any]


class ReactivePrivilegedPlanner(BoundPlanner):
    """PRIVILEGED: a receding-horizon beam search over the robot's motions in which every candidate step is rolled
    through the environment's reaction model, so the pedestrians of a plan are those its motions produce.

    Layers of one control step. From every state of a layer, :func:`agents.planners.search.motion_candidates` (16
    headings around the full circle x 3 speeds, 3 goal-directed speeds -- the fastest arriving exactly --, standing:
    52 velocities) are commanded as the environment commands them (the float32 action, scaled and capped as
    ``env.step`` does: :func:`env_velocities`). The children of the whole layer are rolled out lazily, one control
    step each from the parent's crowd (``parent.end.simulate``), nearest the goal first (the heuristic) -- after the
    first layer, those that a cheap guess finds clear (the parent's crowd moving on at its last velocities) before the
    others --: a child is kept when its robot path stays ``robot_radius_m + pedestrian_radius_m + margin_m`` or
    farther from every present pedestrian at every physics substep end (where the world checks contacts) and no kept
    child of the layer lies in its ``cell_m`` lattice cell. At most ``beam`` children are kept per layer, and at most
    ``4 beam`` roll-outs tried (every first motion may be tried). The first child on the goal ends the search (the
    fastest arrival found); otherwise, after ``horizon_steps`` layers (or the episode's last step, or the last layer
    any state survived) the state nearest the goal gives a partial plan, and the search is made again keeping
    ``wide_beam`` per layer, whose plan is taken.

    A plan that reaches the goal is followed to its end; a partial one for ``replan_steps`` steps, then the search
    starts again from where the robot is. A plan is followed only while the episode is what it predicted -- the robot
    where the plan put it and every pedestrian's presence and position the plan's, bit for bit (a roll-out is the
    environment's own step) --, else it is replanned at once. When no first motion is clear, the robot takes the one
    whose closest approach is largest (an escape; the episode may be lost either way). Holonomic kinematics and a
    reacting crowd only (under ``reaction="none"`` the replay ceiling, ``make_planner("privileged")``, reads the true
    future).

    Args:
        env_config: the environment's configuration.
        env: an environment to bind at once (single-environment use).
        beam: states kept per layer (>= 1).
        wide_beam: states kept per layer in the second search, made when the first does not reach the goal (>= beam;
            equal: none).
        horizon_steps: layers searched, control steps (>= 1; at most the steps left in the episode).
        replan_steps: steps of a partial plan followed before searching again (>= 1).
        cell_m: lattice of the de-duplication, metres (> 0).
        margin_m: gap kept beyond touching at the substep ends, metres (>= 0).
        headings_deg: headings relative to the goal direction, degrees.
        speed_fractions: speeds as fractions of the preferred speed, in (0, 1].
    """

    label = "the privileged reactive planner"

    def __init__(
        self,
        env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
        env: Any = None,
        beam: int = 3,
        wide_beam: int = 24,
        horizon_steps: int = 40,
        replan_steps: int = 5,
        cell_m: float = 0.2,
        margin_m: float = 0.01,
        headings_deg: Sequence[float] = SEARCH_HEADINGS_DEG,
        speed_fractions: Sequence[float] = SEARCH_SPEED_FRACTIONS,
    ) -> None:
        super().__init__(env_config if env_config is not None or env is None else env.unwrapped.config)
        self._check_env(self.cfg)
        for key, value, least in (
            ("beam", beam, 1),
            ("wide_beam", wide_beam, beam),
            ("horizon_steps", horizon_steps, 1),
            ("replan_steps", replan_steps, 1),
        ):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < least:
                what = "beam" if key == "wide_beam" else least
                raise ValueError(
                    f"privileged reactive planner option {key!r}: got {value!r}; allowed: an integer >= {what}"
                )
        for key, value, allowed in (
            ("cell_m", cell_m, "a finite number > 0 (metres)"),
            ("margin_m", margin_m, "a finite number >= 0 (metres)"),
        ):
            ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
            if not ok or value < 0 or (key == "cell_m" and value == 0):
                raise ValueError(f"privileged reactive planner option {key!r}: got {value!r}; allowed: {allowed}")
        try:
            self.headings, self.fractions = _fractions_and_headings(headings_deg, speed_fractions)
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"privileged reactive planner options 'headings_deg' / 'speed_fractions': got {headings_deg!r} / "
                f"{speed_fractions!r}; allowed: non-empty lists of degrees / of fractions in (0, 1] ({exc})"
            ) from None
        self.beam = int(beam)
        self.wide_beam = int(wide_beam)
        self.horizon_steps = int(horizon_steps)
        self.replan_steps = int(replan_steps)
        self.cell_m = float(cell_m)
        self.contact_m = self.cfg.robot_radius_m + self.cfg.pedestrian_radius_m + float(margin_m)
        self.stats = ReactivePlannerStats()
        self._envs: list[Any] = []
        self._plans: dict[int, ReactivePlan] = {}
        if env is not None:
            self.bind_envs([env])

    # ------------------------------------------------------------------ the SB3 interface

    def _check_env(self, config: CrowdNavConfig) -> None:
        _check_env_config(config)

    def _action(self, env: Any) -> np.ndarray:
        plan = self._plans.get(id(env))
        if plan is None or not self._on_plan(env, plan):
            plan = self.plan(env)
            self._plans[id(env)] = plan
        return plan.actions[env.steps_taken - plan.start_step].copy()

    def _on_plan(self, env: Any, plan: ReactivePlan) -> bool:
        """The episode is where ``plan`` said it would be and the plan has a step left to follow."""
        k = env.steps_taken - plan.start_step
        if plan.episode is not env.episode or not 0 <= k < len(plan.actions):
            return False
        if not plan.reaches_goal and k >= self.replan_steps:
            return False
        if k == 0:
            return True
        if not np.array_equal(env.robot_position, plan.positions[k]):
            return False
        positions, present = env.pedestrians
        return bool(
            np.array_equal(present, plan.present[k - 1])
            and np.array_equal(positions[present], plan.crowd[k - 1][present])
        )

    # ------------------------------------------------------------------ planning

    def plan(self, env: Any) -> ReactivePlan:
        """A contact-free plan from the environment's current state against the crowd's replies (see the class doc)."""
        started = time.perf_counter()
        env = getattr(env, "unwrapped", env)
        ep = env.episode
        if ep is None:
            raise RuntimeError("the environment has no episode: call reset() first")
        self._check_env(env.config)
        n0 = env.steps_taken
        steps = min(self.horizon_steps, ep.max_steps - n0)
        if steps <= 0:
            raise RuntimeError(f"the episode has no step left (step {n0} of {ep.max_steps})")
        snapshot = env.reaction_snapshot()
        goal = np.asarray(ep.goal, dtype=np.float64)
        plan = self._search(snapshot, goal, steps, self.beam)
        if not plan.reaches_goal and plan.contact_free and self.wide_beam > self.beam:
            narrow = plan.simulations
            plan = self._search(snapshot, goal, steps, self.wide_beam)
            plan.simulations += narrow
            plan.widened = True
        plan.episode, plan.start_step = ep, n0
        plan.seconds = time.perf_counter() - started
        st = self.stats
        st.plans += 1
        st.found += int(plan.reaches_goal)
        st.widened += int(plan.widened)
        st.escapes += int(not plan.contact_free)
        st.simulations += plan.simulations
        st.seconds += plan.seconds
        return plan

    def _gap(self, rollout: Any) -> float:
        """Smallest centre distance from the robot to a present pedestrian at the substep ends after the start."""
        robot, peds, present = rollout.robot[1:], rollout.positions[1:], rollout.present[1:]
        if not present.any():
            return math.inf
        d = np.hypot(peds[..., 0] - robot[:, None, 0], peds[..., 1] - robot[:, None, 1])
        return float(np.where(present, d, np.inf).min())

    def _predicted_gaps(
        self,
        xs: np.ndarray,
        cmd: np.ndarray,
        h: float,
        s: int,
        crowd: list[np.ndarray],
        velocity: list[np.ndarray],
        present: list[np.ndarray],
    ) -> np.ndarray:
        """``(M, A)`` smallest centre distance over a step's substep ends from states ``xs`` ``(M, 2)`` moving at
        ``cmd`` ``(M, A, 2)`` to each state's crowd moving on at its last velocities (``(N, 2)`` positions and velocities,
        ``(N,)`` presence per state): a cheap guess of the roll-out's, which only orders the roll-outs."""
        peds, vel, here = np.stack(crowd), np.stack(velocity), np.stack(present)  # (M, N, 2), (M, N, 2), (M, N)
        reach = self.cfg.robot_pref_speed_mps * self.cfg.dt_s + self.contact_m + np.hypot(vel[..., 0], vel[..., 1])
        lo, hi = xs.min(axis=0), xs.max(axis=0)
        near = here & np.all((peds >= lo - reach[..., None]) & (peds <= hi + reach[..., None]), axis=-1)
        cols = np.flatnonzero(near.any(axis=0))
        if not len(cols):
            return np.full(cmd.shape[:2], np.inf)
        peds, vel, near = peds[:, cols], vel[:, cols], near[:, cols]
        k = h * np.arange(1, s + 1)[:, None, None, None]  # (S, 1, 1, 1) seconds
        robot = xs[None, :, None, :] + k * cmd[None]  # (S, M, A, 2)
        where = peds[None] + k * vel[None]  # (S, M, P, 2)
        d = np.hypot(robot[..., None, 0] - where[:, :, None, :, 0], robot[..., None, 1] - where[:, :, None, :, 1])
        return np.where(near[None, :, None, :], d, np.inf).min(axis=(0, 3))

    def _search(self, snapshot: Any, goal: np.ndarray, steps: int, beam: int) -> ReactivePlan:
        """The beam search from ``snapshot`` over at most ``steps`` layers keeping ``beam`` states per layer (episode
        and timing filled by :meth:`plan`)."""
        cfg = self.cfg
        v, dt, s = cfg.robot_pref_speed_mps, cfg.dt_s, cfg.substeps
        h = snapshot.substep_s
        tol = cfg.goal_tolerance_m - 1e-9
        robot = np.asarray(snapshot.robot, dtype=np.float64)
        base = math.atan2(goal[1] - robot[1], goal[0] - robot[0])
        xs, ends = robot[None], [snapshot]
        layers: list[_Layer] = []
        sims = 0
        for j in range(steps):
            vel = motion_candidates(xs, goal, base, v, dt, self.headings, self.fractions)  # (M, A, 2)
            action, _ = command_velocities(vel, v)
            cmd = env_velocities(action, v)
            end = xs[:, None, :]
            for _ in range(s):  # as the world integrates (robot_path): p += v h per substep
                end = end + cmd * h
            a_n = vel.shape[1]
            to_goal = np.hypot(goal[0] - end[..., 0], goal[1] - end[..., 1]).reshape(-1)
            cells = np.floor(end.reshape(-1, 2) / self.cell_m).astype(np.int64)
            if j == 0:  # every first motion may be tried, nearest the goal first
                order, tries = np.argsort(to_goal, kind="stable"), len(to_goal)
            else:  # the motions clear of the crowd moving on at its last velocities first, each nearest the goal first
                last = layers[-1]
                clear = self._predicted_gaps(xs, cmd, h, s, last.crowd, last.velocity, last.present) >= self.contact_m
                order, tries = np.lexsort((to_goal, ~clear.reshape(-1))), _TRIES_PER_STATE * beam
            layer = _Layer([], [], [], [], [], [], [])
            taken: set[tuple[int, int]] = set()
            arrived = False
            for i in order.tolist():
                cell = (int(cells[i, 0]), int(cells[i, 1]))
                if cell in taken:
                    continue
                if tries == 0:
                    break
                tries -= 1
                m, a = divmod(i, a_n)
                rollout = ends[m].simulate(cmd[m, a][None])
                sims += 1
                if self._gap(rollout) < self.contact_m:
                    continue
                taken.add(cell)
                layer.parent.append(m)
                layer.action.append(action[m, a])
                layer.robot.append(rollout.robot[-1])
                layer.crowd.append(rollout.positions[-1])
                layer.present.append(rollout.present[-1])
                moving = rollout.present[-1] & rollout.present[-2]
                step = (rollout.positions[-1] - rollout.positions[-2]) / h
                layer.velocity.append(np.where(moving[:, None], step, 0.0))
                layer.ends.append(rollout.end)
                if to_goal[i] <= tol:
                    arrived = True
                    break
                if len(layer.parent) == beam:
                    break
            if not layer.parent:
                break
            layers.append(layer)
            if arrived:
                return self._backtrack(robot, layers, len(layer.parent) - 1, True, sims)
            for older in layers[:-1]:
                older.ends = []
            xs, ends = np.stack(layer.robot), layer.ends
        if not layers:
            return self._escape(snapshot, robot, goal, base, sims)
        return self._backtrack(robot, layers, 0, False, sims)  # kept in order of distance to the goal: 0 is nearest

    def _backtrack(self, robot: np.ndarray, layers: list[_Layer], index: int, reached: bool, sims: int) -> ReactivePlan:
        """The plan ending at state ``index`` of the last layer."""
        actions, positions, crowd, present = [], [], [], []
        for layer in reversed(layers):
            actions.append(layer.action[index])
            positions.append(layer.robot[index])
            crowd.append(layer.crowd[index])
            present.append(layer.present[index])
            index = layer.parent[index]
        positions.append(robot)
        return ReactivePlan(
            None,
            0,
            np.stack(actions[::-1]).astype(np.float32),
            np.stack(positions[::-1]),
            np.stack(crowd[::-1]),
            np.stack(present[::-1]),
            reaches_goal=reached,
            contact_free=True,
            simulations=sims,
        )

    def _escape(self, snapshot: Any, robot: np.ndarray, goal: np.ndarray, base: float, sims: int) -> ReactivePlan:
        """No first motion is clear: the one whose closest approach is largest, as a one-step plan."""
        v, dt = self.cfg.robot_pref_speed_mps, self.cfg.dt_s
        vel = motion_candidates(robot, goal, base, v, dt, self.headings, self.fractions)  # (A, 2)
        action, _ = command_velocities(vel, v)
        cmd = env_velocities(action, v)
        best, best_gap = None, -math.inf
        for a in range(len(cmd)):
            rollout = snapshot.simulate(cmd[a][None])
            sims += 1
            gap = self._gap(rollout)
            if gap > best_gap:
                best, best_gap = (a, rollout), gap
        assert best is not None
        a, rollout = best
        return ReactivePlan(
            None,
            0,
            action[a][None].astype(np.float32),
            np.stack([robot, rollout.robot[-1]]),
            rollout.positions[-1][None],
            rollout.present[-1][None],
            reaches_goal=False,
            contact_free=False,
            simulations=sims,
        )


def _check_env_config(cfg: CrowdNavConfig) -> None:
    """``ValueError`` unless the environment has a reacting crowd and holonomic kinematics."""
    if cfg.reaction == "none":
        raise ValueError(
            "the privileged reactive planner plans against a reaction model, but the environment's reaction is 'none' "
            "(the replay): use the replay ceiling there, make_planner('privileged') without reactive=True"
        )
    if cfg.kinematics != "holonomic":
        raise ValueError(
            f"the privileged reactive planner plans holonomic motions; kinematics {cfg.kinematics!r} is not supported"
        )
