"""Rule 3: a robot in the path of a crowd is avoided where the replay walks into it; and the ORCA responsibility
choice (RVO2's reciprocal halves, solved again every substep) holds against a robot that does not give way."""

from __future__ import annotations

import numpy as np
import pytest

from envs.reaction import ReactionParams

#: How far inside the contact distance a centre may come and still count as not hit, metres (ORCA's one-step
#: tolerance in single precision: a few millimetres at most).
SLACK_M = 0.01


def closest(trace) -> float:
    """The smallest robot-pedestrian centre distance over the run, metres."""
    return float(trace.robot_distance().min())


def test_the_replay_walks_into_a_standing_robot(kit) -> None:
    trace = kit.simulate("none", kit.head_on_recording(), np.zeros(2))
    assert closest(trace) < kit.contact_m - 0.3
    assert (trace.robot_distance() < kit.contact_m).any(axis=0).sum() >= 10  # most of the 20 walk through it


@pytest.mark.parametrize("dt_s", [0.1, 0.4], ids=["substeps", "control steps"])
@pytest.mark.parametrize("model", ["orca", "social_force", "pause"])
def test_a_standing_robot_is_not_hit(kit, model: str, dt_s: float) -> None:
    """Twenty pedestrians walk head-on at a robot standing at the origin, at lateral offsets of -1..1 m; the model
    stepped at the physics substep (0.1 s) or at the control step (0.4 s)."""
    trace = kit.simulate(model, kit.head_on_recording(), np.zeros(2), dt_s=dt_s)
    assert trace.reacted.any(axis=0).sum() >= 5
    assert closest(trace) >= kit.contact_m - SLACK_M


def driving_head_on(kit, model: str, params: ReactionParams | None = None):
    """The robot drives at 1 m/s against the crowd, from x = 6 m to -5 m in 11 s: pedestrians appear (at x = -8 m)
    at least 3.2 m from it, beyond the trigger distance, so each sees it coming."""
    robot = kit.moving_robot((6.0, 0.0), (-1.0, 0.0))
    return kit.simulate(model, kit.head_on_recording(), robot, seconds=11.0, params=params)


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_a_robot_driving_head_on_into_the_crowd_is_avoided(kit, model: str) -> None:
    """ORCA's pedestrians count on the robot to take half of each avoidance, which it never does; solved again at
    every substep, they take the rest. The social force's see the robot's motion through Helbing & Molnár's ellipse."""
    trace = driving_head_on(kit, model)
    assert trace.reacted.any(axis=0).sum() >= 5
    assert closest(trace) >= kit.contact_m - SLACK_M


def test_a_circular_robot_potential_is_not_enough(kit) -> None:
    """Why the social force's robot potential is an ellipse along the robot's motion: a circular one (the robot's
    step set to 0) lets the robot driving head-on reach the pedestrians."""
    trace = driving_head_on(kit, "social_force", ReactionParams(sf_robot_step_s=0.0))
    assert closest(trace) < kit.contact_m - 0.1


def test_the_check_catches_pedestrians_blind_to_the_robot(kit, monkeypatch: pytest.MonkeyPatch) -> None:
    """ORCA without the robot among its agents (pedestrians that react to each other but not to the robot) hits it."""
    import envs.reaction.orca as orca

    real = orca.OrcaCrowd._model_velocities

    def blind(self, hood):
        hood.robot = hood.robot + 1000.0
        return real(self, hood)

    monkeypatch.setattr(orca.OrcaCrowd, "_model_velocities", blind)
    trace = kit.simulate("orca", kit.head_on_recording(), np.zeros(2))
    assert closest(trace) < kit.contact_m - SLACK_M
