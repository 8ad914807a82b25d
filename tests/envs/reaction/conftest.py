"""Fixtures of the reaction-model tests: scripted crowds (made in code) and a loop that steps a model through them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from envs.reaction import ReactionParams, make_reactive_crowd
from envs.reaction.base import ReactiveCrowd
from envs.recordings import scripted_recording
from envs.replay import Replay

#: The environment's default radii and physics substep.
ROBOT_RADIUS_M = 0.3
PED_RADIUS_M = 0.3
CONTACT_M = ROBOT_RADIUS_M + PED_RADIUS_M
SUBSTEP_S = 0.1


@dataclass
class Trace:
    """A run of a model over ``K`` steps of ``dt_s``, with the recording beside it (row ``k``: time ``t0 + k dt``).

    Attributes:
        times: ``(K + 1,)`` seconds.
        positions: ``(K + 1, N, 2)`` actual positions; present: ``(K + 1, N)``.
        recorded: ``(K + 1, N, 2)`` recorded positions; recorded_present: ``(K + 1, N)``.
        velocities: ``(K, N, 2)`` returned per step; reacting: ``(K, N)`` at each step's end; shift: ``(K, N)``.
        reacted: ``(K, N)`` the pedestrian was moved by the model during the step (reacting at its start or end).
        robot: ``(K + 1, 2)`` the robot's centre.
        crowd: the model after the run.
        steps: every :class:`~envs.reaction.base.CrowdStep`.
    """

    times: np.ndarray
    positions: np.ndarray
    present: np.ndarray
    recorded: np.ndarray
    recorded_present: np.ndarray
    velocities: np.ndarray
    reacting: np.ndarray
    reacted: np.ndarray
    shift: np.ndarray
    robot: np.ndarray
    crowd: ReactiveCrowd
    steps: list
    dt_s: float

    def robot_distance(self) -> np.ndarray:
        """``(K + 1, N)`` centre distance to the robot where present, inf elsewhere."""
        d = np.hypot(*(self.positions - self.robot[:, None, :]).transpose(2, 0, 1))
        return np.where(self.present, d, np.inf)


def head_on_recording(num: int = 20, speed_mps: float = 1.3, spread_m: float = 1.0, gap_steps: int = 3):
    """``num`` pedestrians walking along +x from x = -8 m at ``speed_mps``, one every ``gap_steps`` annotations, at
    lateral offsets spread evenly over [-spread, spread] m: head-on at anything standing near the origin."""
    step = 0.4
    length = int(20.0 / (speed_mps * step)) + 1
    trajs, starts = [], []
    for k in range(num):
        y = -spread_m + 2.0 * spread_m * k / max(num - 1, 1)
        xs = -8.0 + speed_mps * step * np.arange(length)
        trajs.append(np.stack([xs, np.full(length, y)], axis=1))
        starts.append(gap_steps * k)
    return scripted_recording(trajs, starts, name="head-on")


def line_recording(start: tuple[float, float], velocity: tuple[float, float], seconds: float, wobble_m: float = 0.0):
    """One pedestrian walking straight from ``start`` at ``velocity`` for ``seconds`` (annotations every 0.4 s),
    with an optional deterministic sideways wobble of ``wobble_m`` (a noisy annotation)."""
    n = int(seconds / 0.4) + 1
    t = 0.4 * np.arange(n)
    pos = np.asarray(start) + np.outer(t, velocity)
    if wobble_m:
        normal = np.array([-velocity[1], velocity[0]]) / np.hypot(*velocity)
        pos = pos + wobble_m * np.sin(1.7 * np.arange(n))[:, None] * normal
    return pos


def simulate(
    model: str,
    recording,
    robot: Callable[[float], tuple[np.ndarray, np.ndarray]] | np.ndarray,
    seconds: float | None = None,
    params: ReactionParams | None = None,
    dt_s: float = SUBSTEP_S,
) -> Trace:
    """Step ``model`` through ``recording`` (from its first annotation) with the robot at ``robot(t) -> (position,
    velocity)`` (or standing at a fixed ``(2,)`` position)."""
    replay = Replay(recording)
    crowd = make_reactive_crowd(model, params, robot_radius_m=ROBOT_RADIUS_M, pedestrian_radius_m=PED_RADIUS_M)
    t0 = replay.t_start_s
    crowd.reset(replay, t0)
    total = replay.t_end_s - t0 if seconds is None else seconds
    num = round(total / dt_s)
    if callable(robot):
        where = robot
    else:
        standing = np.asarray(robot, dtype=float)

        def where(t: float) -> tuple[np.ndarray, np.ndarray]:
            return standing, np.zeros(2)

    times = t0 + dt_s * np.arange(num + 1)
    rec, rec_present = replay.positions_at(times)
    n = replay.num_pedestrians
    positions = np.empty((num + 1, n, 2))
    present = np.empty((num + 1, n), dtype=bool)
    positions[0], present[0] = crowd.positions, crowd.present
    velocities = np.zeros((num, n, 2))
    reacting = np.zeros((num, n), dtype=bool)
    shift = np.zeros((num, n))
    robot_path = np.empty((num + 1, 2))
    steps = []
    for k in range(num):
        p, v = where(times[k])
        robot_path[k] = p
        out = crowd.step(times[k], dt_s, rec[k], rec_present[k], rec[k + 1], rec_present[k + 1], p, v)
        steps.append(out)
        positions[k + 1], present[k + 1] = out.positions, out.present
        velocities[k], reacting[k], shift[k] = out.velocities, out.reacting, out.shift_s
    robot_path[num] = where(times[num])[0]
    before = np.vstack([np.zeros((1, n), dtype=bool), reacting[:-1]])
    return Trace(
        times, positions, present, rec, rec_present, velocities, reacting, before | reacting, shift, robot_path,
        crowd, steps, dt_s,
    )  # fmt: skip


def moving_robot(start: tuple[float, float], velocity: tuple[float, float], t0: float = 0.0, stop_s: float = np.inf):
    """A robot standing at ``start`` until ``t0``, then moving at ``velocity`` for ``stop_s`` seconds, then standing."""
    start_a, vel = np.asarray(start, dtype=float), np.asarray(velocity, dtype=float)

    def where(t: float) -> tuple[np.ndarray, np.ndarray]:
        tau = min(max(t - t0, 0.0), stop_s)
        return start_a + vel * tau, (vel.copy() if 0.0 <= t - t0 < stop_s else np.zeros(2))

    return where


@pytest.fixture
def kit() -> SimpleNamespace:
    """The helpers above, for the tests (the test modules cannot import this file)."""
    return SimpleNamespace(
        simulate=simulate,
        head_on_recording=head_on_recording,
        line_recording=line_recording,
        moving_robot=moving_robot,
        scripted_recording=scripted_recording,
        contact_m=CONTACT_M,
        dt_s=SUBSTEP_S,
    )
