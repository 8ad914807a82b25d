"""The environment's side of the reaction models (``reaction=`` other than ``none``): an episode's reacting crowd as
the world moves it, what the robot's tracker records of it, and roll-outs of the model for privileged planners.

:class:`envs.crowd_nav.CrowdNavEnv` uses this module only when ``reaction`` is ``pause``, ``orca`` or
``social_force``; under ``none`` nothing of it exists and episodes are the plain replay's. The models themselves are
:mod:`envs.reaction` (``docs/reaction.md``). The rules of the environment around them:

* **When the model decides** (:data:`STEPPING`): at every physics substep (0.1 s), for every model. ``pause``'s rule
  is a contact check one substep ahead (a pedestrian and the robot close up to 1 m in a 0.4 s control step, more
  than its margin); the social force's robot potential is stiff (explicit Euler needs steps under about 0.13 s);
  ORCA leaves half of each avoidance to the robot, which does not take it, so a pedestrian takes the rest at its next
  decision: decided once per control step (``stepping="control"``: the substeps on the straight line between its
  ends, which is the model's motion) a robot standing in univ's crowds ended 14 of 35 episodes in a collision, every
  substep 1 of 26 (the replay: 19 of 38). Steps in which nobody reacts or is triggered cost next to nothing
  (:meth:`envs.reaction.ReactiveCrowd.advance`). ``benchmarks/env_speed.py --reaction-only`` measures both.
* **The robot as the pedestrians see it**: its centre at the start of a model step and its velocity over the
  previous model step (causal: nobody sees the command the robot is about to execute; 0 at the episode's start,
  where the robot is at rest). Pedestrians never see the forecasts, the goal or the policy.
* **Pop-in ghosts** (:mod:`envs.popin`) take no part in the model until they are real: the model is told they are
  absent, so they move as recorded, react to nothing and nobody avoids them; from the checkpoint at which they become
  real they start on their recording. The pop-in rule reads the recording (where a ghost is).
* **The future** (rows ``1..H`` of a step: the intrusion term and the ``oracle`` forecasts) stays the recording, what
  each person would have done without the robot from now on: a counterfactual once people react. For ``pause``, a
  pedestrian's own time-shifted recording, ``recorded(t + h dt - shift)``, the model's plan for it.
* **Perception** (:class:`ObservedReplay`): the robot's tracker reports the positions pedestrians actually had at the
  annotation times, as it reports recorded ones under ``none`` (latest annotation at or before ``t``; velocities the
  slopes between successive annotations), the recording before the episode's start. An annotation between two substep
  ends (``biwi_eth``) holds a reacting pedestrian's position extrapolated from the substep end before it (its
  velocity over the substep before that), so what the robot observes at ``t`` depends on nothing after ``t``.
* **Forecasts** (:mod:`envs.forecasting.observed`): from those observed histories. Where nobody observed in a
  forecast's history window was off the recording, the observed histories are the recorded ones and the per-recording
  cache holds the forecast; elsewhere it is computed from the observed histories, for the whole scene with a social
  predictor (per pedestrian for constant velocity).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np

from envs.popin import PopInRule
from envs.reaction import CrowdStep, DisturbanceMetrics, ReactionParams, make_reactive_crowd
from envs.replay import TIME_TOL_S, Replay
from envs.world import robot_path

#: How often each model decides: ``substep`` (every physics substep) or ``control`` (once per control step, the
#: substeps on the straight line between its ends). See the module docstring.
STEPPING: Final[dict[str, str]] = {"pause": "substep", "orca": "substep", "social_force": "substep"}
#: Values of :attr:`ReactiveWorld.stepping`.
STEPPINGS: Final[tuple[str, ...]] = ("substep", "control")


class ObservedReplay(Replay):
    """What the robot's tracker records of an episode's pedestrians: the replay's annotations, in which a pedestrian
    that was off its recording (reacting, or time-shifted by ``pause``) has where it actually was at the annotation's
    time. It is a :class:`~envs.replay.Replay` (``perceived_at``, ``positions_at``, ``positions``, ``present``, ...),
    so perception, forecasts and uncertainty read it as they read the replay under ``none``. Annotations after the
    current time hold the recording until the episode reaches them; perception never reads them.

    Args:
        replay: the episode's replay (annotation times, rows, recorded values).

    Attributes:
        replay: that replay.
        deviated: ``(F,)`` bool: at annotation ``i`` some pedestrian was recorded off its recording.
    """

    def __init__(self, replay: Replay) -> None:
        # the replay's state, copied (nothing recomputed)
        vars(self).update({k: v.copy() if isinstance(v, np.ndarray) else v for k, v in vars(replay).items()})
        self.replay = replay
        self.deviated = np.zeros(len(self.times), dtype=bool)
        self._deviated_count = np.zeros(len(self.times) + 1, dtype=np.int64)  # cumulative, for window queries

    def record(self, index: int, rows: np.ndarray, positions: np.ndarray, present: np.ndarray) -> None:
        """Annotation ``index`` of pedestrians ``rows`` ``(m,)``: where they were ``(m, 2)`` metres and whether present
        ``(m,)``, replacing the recorded values; the annotation counts as deviated. Velocities and presence between
        annotations follow, computed as :class:`~envs.replay.Replay` computes them (same floats)."""
        if not len(rows):
            return
        self.positions[index, rows] = positions
        self.present[index, rows] = present
        if not self.deviated[index]:
            self.deviated[index] = True
            self._deviated_count[index + 1 :] += 1
        self._refresh(index)

    def _refresh(self, i: int) -> None:
        """Derived arrays around annotation ``i`` (the intervals ending and starting there, the velocities at
        ``i - 1 .. i + 1``), with :class:`~envs.replay.Replay`'s formulas."""
        f = len(self.times)
        a, b = max(i - 1, 0), min(i + 1, f - 1)  # the intervals from annotation j to j + 1, j in [a, b)
        if a < b:
            valid = self.present[a:b] & self.present[a + 1 : b + 1]
            slope = (self.positions[a + 1 : b + 1] - self.positions[a:b]) / (
                self.times[a + 1 : b + 1] - self.times[a:b]
            )[:, None, None]
            self.valid[a:b] = valid
            self.slopes[a:b] = np.where(valid[..., None], slope, 0.0)
            self._presence[a:b, 1] = valid
        self._presence[i, 0] = self.present[i]
        c, d = max(i - 1, 1), min(i + 2, f)  # the velocities at annotations j in [c, d) (none arrives at 0)
        if c < d:
            arrival = np.where(self.valid[c - 1 : d - 1, :, None], self.slopes[c - 1 : d - 1], 0.0)
            self.arrival_velocity[c:d] = arrival
            self.annotation_velocity[c:d] = np.where(self.valid[c:d, :, None], self.slopes[c:d], arrival)
        if i <= 1:  # annotation 0: no arrival
            self.arrival_velocity[0] = 0.0
            self.annotation_velocity[0] = np.where(self.valid[0][:, None], self.slopes[0], 0.0)

    def deviated_between(self, t_from_s: float, t_to_s: float) -> bool:
        """Some annotation in ``[t_from_s, t_to_s]`` (seconds, inclusive up to :data:`~envs.replay.TIME_TOL_S`) was
        recorded off the recording."""
        lo, hi = np.searchsorted(self.times, (t_from_s - TIME_TOL_S, t_to_s + TIME_TOL_S), "left")
        return bool(self._deviated_count[hi] - self._deviated_count[lo])


@dataclass(frozen=True)
class CrowdMotion:
    """The pedestrians over one control step, as the world places them.

    Attributes:
        positions: ``(S + 1, N, 2)`` metres at the substep ends (row 0: the step's start).
        present: ``(S + 1, N)`` bool (pop-in ghosts absent).
        last: the model's :class:`~envs.reaction.CrowdStep` at the step's end.
    """

    positions: np.ndarray
    present: np.ndarray
    last: CrowdStep


class ReactiveWorld:
    """An episode's pedestrians under a reaction model, as the environment moves them (see the module docstring).

    Args:
        model: ``pause``, ``orca`` or ``social_force``.
        params: the models' constants.
        robot_radius_m: the robot's radius, metres.
        pedestrian_radius_m: the pedestrians' radius, metres.
        stepping: ``substep`` or ``control`` (default: :data:`STEPPING` of the model).

    Attributes:
        crowd: the model (:class:`~envs.reaction.ReactiveCrowd`).
        observed: the tracker's record of the episode (:class:`ObservedReplay`; after :meth:`reset`).
        metrics: the episode's :class:`~envs.reaction.DisturbanceMetrics`.
        robot_velocity: ``(2,)`` m/s: the robot's velocity as the pedestrians see it at the next model step.
        departures: per control step of the episode, the pedestrians off their recording at its end: ``(rows (m,),
            positions (m, 2), presence (m,))`` (the world is the recording elsewhere).
        future_departures: at the last step, the pedestrians whose future differs from the recording (``pause``'s
            time-shifted ones): ``(rows (m,), positions (H, m, 2), presence (H, m))``.
        forecast_memo: the episode's forecasts from observed histories per annotation frame
            (:func:`envs.forecasting.observed.observed_forecasts`).
    """

    def __init__(
        self,
        model: str,
        params: ReactionParams,
        robot_radius_m: float,
        pedestrian_radius_m: float,
        stepping: str | None = None,
    ) -> None:
        if model not in STEPPING:
            raise ValueError(f"ReactiveWorld is for the models {', '.join(STEPPING)}, got {model!r}")
        stepping = STEPPING[model] if stepping is None else stepping
        if stepping not in STEPPINGS:
            raise ValueError(f"stepping must be one of {', '.join(STEPPINGS)}, got {stepping!r}")
        self.model = model
        self.params = params
        self.stepping = stepping
        self.crowd = make_reactive_crowd(
            model, params, robot_radius_m=robot_radius_m, pedestrian_radius_m=pedestrian_radius_m
        )
        self.metrics = DisturbanceMetrics(params.on_track_tolerance_m)
        self.robot_velocity = np.zeros(2)
        self.observed: ObservedReplay | None = None
        self.last: CrowdStep | None = None
        self._before: tuple[float, np.ndarray, np.ndarray] | None = None
        self.departures: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.forecast_memo: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.future_departures: tuple[np.ndarray, np.ndarray, np.ndarray] = (
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 0, 2)),
            np.zeros((0, 0), dtype=bool),
        )

    def reset(self, replay: Replay, t0_s: float) -> None:
        """Start an episode at ``t0_s``: everyone on its recording, the robot at rest, nothing measured yet."""
        self.crowd.reset(replay, t0_s)
        self.observed = ObservedReplay(replay)
        self.metrics = DisturbanceMetrics(self.params.on_track_tolerance_m)
        self.robot_velocity = np.zeros(2)
        self.last = None
        self._before: tuple[float, np.ndarray, np.ndarray] | None = None  # the last step's second-to-last substep end
        self.departures = []
        self.future_departures = (np.zeros(0, dtype=np.int64), np.zeros((0, 0, 2)), np.zeros((0, 0), dtype=bool))
        self.forecast_memo = {}

    def clone(self) -> ReactiveWorld:
        """A copy in the current state for roll-outs: its own model state; no record, no metrics."""
        twin = copy.copy(self)
        twin.crowd = self.crowd.clone()
        twin.robot_velocity = self.robot_velocity.copy()
        twin.observed = None
        twin.metrics = DisturbanceMetrics(self.params.on_track_tolerance_m)
        twin.departures = []
        return twin

    # ------------------------------------------------------------------ a control step

    def move(
        self,
        times_s: np.ndarray,
        recorded: np.ndarray,
        present: np.ndarray,
        ghost: np.ndarray | None,
        robot: np.ndarray,
        substep_s: float,
        bookkeeping: bool = True,
    ) -> CrowdMotion:
        """Move the pedestrians over one control step of ``S`` physics substeps.

        Args:
            times_s: ``(S + 1,)`` the substep ends, seconds (row 0: the step's start, the model's current time).
            recorded: ``(S + 1, N, 2)`` recorded positions there, metres.
            present: ``(S + 1, N)`` recorded presence there.
            ghost: ``(S + 1, N)`` pop-in ghosts there (:meth:`envs.popin.PopInRule.step`), or None for none.
            robot: ``(S + 1, 2)`` the robot's centre there, metres.
            substep_s: the physics substep, seconds.
            bookkeeping: record the annotations of the step in :attr:`observed` and update :attr:`metrics` (False in
                roll-outs).

        Returns:
            the pedestrians at the substep ends: on their recording there, the recorded floats; ghosts absent.
        """
        s = len(times_s) - 1
        model_present = present if ghost is None else present & ~ghost
        if self.stepping == "substep":
            seen = np.empty((s, 2))
            seen[0] = self.robot_velocity
            seen[1:] = (robot[1:s] - robot[: s - 1]) / substep_s
            path = self.crowd.advance(float(times_s[0]), substep_s, recorded, model_present, robot, seen)
            self.robot_velocity = (robot[s] - robot[s - 1]) / substep_s
            positions, pres, last = path.positions, path.present, path.last
            if ghost is not None:
                pres = pres & ~ghost
        else:
            p0, pres0 = self.crowd.positions, self.crowd.present
            if ghost is not None:
                pres0 &= ~ghost[0]
            dt_s = float(times_s[s] - times_s[0])
            last = self.crowd.step(
                float(times_s[0]),
                dt_s,
                recorded[0],
                model_present[0],
                recorded[s],
                model_present[s],
                robot[0],
                self.robot_velocity,
            )
            self.robot_velocity = (robot[s] - robot[0]) / dt_s
            positions, pres = recorded.copy(), model_present.copy()
            off = np.flatnonzero(
                _off_record(p0, pres0, recorded[0], model_present[0])
                | _off_record(last.positions, last.present, recorded[s], model_present[s])
            )
            if len(off):  # the model's straight line over the step
                w = (np.arange(s + 1) / s)[:, None, None]
                positions[:, off] = p0[off] + w * (last.positions[off] - p0[off])
                pres[:, off] = pres0[off] & last.present[off]
                pres[0, off], pres[s, off] = pres0[off], last.present[off]
        self.last = last
        if bookkeeping:
            assert self.observed is not None
            off_rows = _off_record(positions, pres, recorded, model_present)
            self._record(times_s, positions, pres, off_rows)
            self._before = (float(times_s[s - 1]), positions[s - 1], pres[s - 1])
            rows = np.flatnonzero(off_rows[s])
            self.departures.append((rows, positions[s, rows], pres[s, rows]))
            self.metrics.update(float(times_s[s]), last, recorded[s], present[s])
        return CrowdMotion(positions, pres, last)

    def _record(self, times_s: np.ndarray, positions: np.ndarray, present: np.ndarray, off: np.ndarray) -> None:
        """Write the annotations in ``(times_s[0], times_s[-1]]`` of the pedestrians off their recording into
        :attr:`observed`, from the world up to the annotation's time only (so perception stays causal): at a substep
        end, the positions there; between two (``biwi_eth``), the pedestrians off their recording at the earlier end,
        extrapolated from it with their velocity over the substep before it (a pedestrian on its recording there keeps
        the annotation)."""
        obs = self.observed
        assert obs is not None
        lo, hi = np.searchsorted(obs.times, (times_s[0] + TIME_TOL_S, times_s[-1] + TIME_TOL_S), "right")
        for j in range(int(lo), int(hi)):
            tau = float(obs.times[j])
            k = int(np.searchsorted(times_s, tau - TIME_TOL_S, "left"))
            if abs(times_s[k] - tau) <= TIME_TOL_S:
                rows = np.flatnonzero(off[k])
                obs.record(j, rows, positions[k, rows], present[k, rows])
                continue
            a = k - 1
            rows = np.flatnonzero(off[a])
            if not len(rows):
                continue
            if a >= 1:
                t_b, p_b, here_b = float(times_s[a - 1]), positions[a - 1, rows], present[a - 1, rows]
            elif self._before is not None:
                t_b, p_b, here_b = self._before[0], self._before[1][rows], self._before[2][rows]
            else:  # the episode's first substep: no velocity yet
                t_b, p_b, here_b = float(times_s[a]), positions[a, rows], np.zeros(len(rows), dtype=bool)
            p_a, here_a = positions[a, rows], present[a, rows]
            moving = (here_a & here_b)[:, None]
            velocity = np.where(moving, (p_a - p_b) / max(float(times_s[a]) - t_b, 1e-9), 0.0)
            obs.record(j, rows, p_a + (tau - float(times_s[a])) * velocity, here_a)

    def future(
        self, replay: Replay, times_s: np.ndarray, recorded: np.ndarray, present: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """What each pedestrian would do without the robot from now on, at ``times_s`` ``(H,)``: the recording
        (``recorded`` ``(H, N, 2)``, ``present`` ``(H, N)``), except for ``pause``'s time-shifted pedestrians, whose own
        recording runs ``shift`` late: ``recorded(t - shift)``."""
        shift = None if self.last is None else self.last.shift_s
        if shift is None or not (shift > 0.0).any():
            self.future_departures = (np.zeros(0, dtype=np.int64), np.zeros((len(times_s), 0, 2)), present[:, :0])
            return recorded, present
        rows = np.flatnonzero(shift > 0.0)
        times = (np.asarray(times_s)[:, None] - shift[rows][None, :]).reshape(-1)
        pos, pres = replay.positions_at(times)
        h, m = len(times_s), len(rows)
        pick = np.arange(h * m).reshape(h, m)
        recorded, present = recorded.copy(), present.copy()
        recorded[:, rows] = pos[pick, rows[None, :]]
        present[:, rows] = pres[pick, rows[None, :]]
        self.future_departures = (rows, recorded[:, rows], present[:, rows])
        return recorded, present


def _off_record(
    positions: np.ndarray, present: np.ndarray, recorded: np.ndarray, recorded_present: np.ndarray
) -> np.ndarray:
    """``(..., N)`` bool: presence differs from the recording's, or present and not at the recorded floats."""
    moved = (positions[..., 0] != recorded[..., 0]) | (positions[..., 1] != recorded[..., 1])
    return (present != recorded_present) | (present & moved)


@dataclass(frozen=True)
class ReactionRollout:
    """The pedestrians over a candidate robot path (:meth:`ReactionSnapshot.simulate`).

    Attributes:
        times_s: ``(T S + 1,)`` the substep ends, seconds (row ``m S``: control step ``m`` from the snapshot).
        positions: ``(T S + 1, N, 2)`` metres, replay rows (row 0: now).
        present: ``(T S + 1, N)`` bool (pop-in ghosts absent).
        robot: ``(T S + 1, 2)`` the robot's centre, metres.
        reacting: ``(T, N)`` bool: moved by the model at the end of each control step.
        end: the crowd at the roll-out's end, to roll on from (a tree search expands a node with
            ``node.end.simulate(...)``).
    """

    times_s: np.ndarray
    positions: np.ndarray
    present: np.ndarray
    robot: np.ndarray
    reacting: np.ndarray
    end: ReactionSnapshot


class ReactionSnapshot:
    """An episode's reacting crowd frozen at one time, to roll the reaction model forward for candidate robot paths.

    A privileged measuring stick (it reads the model and every recorded future; no policy's observation carries
    them): a search planner can score each candidate plan against what the pedestrians would do in reply, and a tree
    search can expand a node from the crowd a roll-out ends with (:attr:`ReactionRollout.end`). Made by
    :meth:`envs.crowd_nav.CrowdNavEnv.reaction_snapshot`; every :meth:`simulate` starts again from the snapshot, and
    neither it nor the environment is changed by it. A roll-out runs exactly the environment's rules (the pop-in
    rule, the model's stepping, the robot's velocity as the pedestrians see it), so executing the same robot
    velocities in the environment gives the same pedestrians, bit for bit (``tests/envs/test_reaction_env.py``); it
    does no physics (contacts end nothing in a roll-out: check distances to :attr:`ReactionRollout.robot`).

    Args:
        world: the episode's reacting crowd (cloned here).
        popin: the episode's pop-in rule (copied here).
        replay: the episode's replay.
        substep_times: function of a control step ``m`` (0 = now) giving its ``(S + 1,)`` substep ends, seconds.
        robot: ``(2,)`` the robot's centre now, metres.
        substep_s: the physics substep, seconds.
    """

    def __init__(
        self,
        world: ReactiveWorld,
        popin: PopInRule,
        replay: Replay,
        substep_times: Callable[[int], np.ndarray],
        robot: np.ndarray,
        substep_s: float,
    ) -> None:
        self.model = world.model
        self._world = world.clone()
        self._popin = copy.deepcopy(popin)
        self._replay = replay
        self._times = substep_times
        self.robot = np.array(robot, dtype=np.float64)
        self.substep_s = float(substep_s)
        self.time_s = float(substep_times(0)[0])

    @property
    def positions(self) -> np.ndarray:
        """``(N, 2)`` the pedestrians' positions now, metres."""
        return self._world.crowd.positions

    @property
    def present(self) -> np.ndarray:
        """``(N,)`` the pedestrians present now (pop-in ghosts included)."""
        return self._world.crowd.present

    def simulate(self, robot_velocities: np.ndarray) -> ReactionRollout:
        """Roll the model forward while the robot moves with ``robot_velocities``.

        Args:
            robot_velocities: ``(T, 2)`` the robot's velocity in each of ``T`` control steps, or ``(T, S, 2)`` in each
                physics substep, m/s, as the environment commands them (an action's velocity after its clipping to
                the preferred speed); the robot moves ``p += v h`` per substep, as in the world.

        Returns:
            the pedestrians and the robot at every substep end of the ``T`` control steps, and the crowd after them.
        """
        world, popin = self._world.clone(), copy.deepcopy(self._popin)
        first = self._times(0)
        s = len(first) - 1
        vel = np.asarray(robot_velocities, dtype=np.float64)
        if vel.ndim == 2:
            vel = np.repeat(vel[:, None, :], s, axis=1)
        if vel.ndim != 3 or vel.shape[1:] != (s, 2) or not np.all(np.isfinite(vel)):
            raise ValueError(f"robot_velocities must be finite, of shape (T, 2) or (T, {s}, 2); got {vel.shape}")
        steps = len(vel)
        n = world.crowd.positions.shape[0]
        times = np.empty(steps * s + 1)
        positions = np.empty((steps * s + 1, n, 2))
        present = np.empty((steps * s + 1, n), dtype=bool)
        robots = np.empty((steps * s + 1, 2))
        reacting = np.zeros((steps, n), dtype=bool)
        times[0], positions[0], present[0], robots[0] = first[0], world.crowd.positions, world.crowd.present, self.robot
        if popin.ghost.any():
            present[0] &= ~popin.ghost
        start = self.robot
        for m in range(steps):
            t = self._times(m)
            path = robot_path(start, [(float(vx), float(vy)) for vx, vy in vel[m]], self.substep_s)
            rec, pres = self._replay.positions_at(t)
            ghost = popin.step(self._replay, t, rec, pres, path)
            motion = world.move(t, rec, pres, ghost, path, self.substep_s, bookkeeping=False)
            rows = slice(m * s + 1, (m + 1) * s + 1)
            times[rows], positions[rows], present[rows] = t[1:], motion.positions[1:], motion.present[1:]
            robots[rows], reacting[m] = path[1:], motion.last.reacting
            start = path[-1]
        end = copy.copy(self)
        end._world, end._popin, end.robot = world, popin, start.copy()
        end._times = _shifted(self._times, steps)
        end.time_s = float(times[-1])
        return ReactionRollout(times, positions, present, robots, reacting, end)


def _shifted(substep_times: Callable[[int], np.ndarray], steps: int) -> Callable[[int], np.ndarray]:
    """``substep_times`` counted from ``steps`` control steps later."""
    return lambda m: substep_times(m + steps)
