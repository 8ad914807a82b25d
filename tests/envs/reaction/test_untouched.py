"""Rule 1: a pedestrian the robot never comes near moves exactly as recorded (bit for bit), under every model; with
the robot far from everyone, every model is ``none``."""

from __future__ import annotations

import numpy as np
import pytest

from envs.reaction import REACTION_MODELS, ReactionParams


def recorded_rows(trace, rows: np.ndarray) -> bool:
    """True when the pedestrians ``rows`` are present exactly where the recording has them and are exactly where it
    has them, at every step (positions compared bit for bit where present)."""
    pres, rec_pres = trace.present[:, rows], trace.recorded_present[:, rows]
    if not np.array_equal(pres, rec_pres):
        return False
    return bool(np.array_equal(trace.positions[:, rows][pres], trace.recorded[:, rows][pres]))


@pytest.mark.parametrize("model", REACTION_MODELS)
def test_a_far_robot_leaves_the_recording_untouched(kit, model: str) -> None:
    trace = kit.simulate(model, kit.head_on_recording(num=8), kit.moving_robot((0.0, 40.0), (0.3, 0.0)))
    assert recorded_rows(trace, np.arange(trace.positions.shape[1]))
    assert not trace.reacting.any()
    assert not trace.shift.any()
    assert all(not s.deviation_m.any() for s in trace.steps)


@pytest.mark.parametrize("model", REACTION_MODELS)
def test_a_pedestrian_out_of_reach_is_untouched_while_others_react(kit, model: str) -> None:
    """A crowd walks head-on at a standing robot (so pedestrians react) while one pedestrian walks a parallel lane
    4 m away, never within the 3 m trigger distance: that one is bit-identical to its recording."""
    lane = kit.head_on_recording(num=10)
    far = kit.line_recording((-8.0, 4.0), (1.3, 0.0), 16.0, wobble_m=0.05)
    num = lane.present.shape[0]
    positions = np.concatenate([lane.positions, np.zeros((num, 1, 2))], axis=1)
    present = np.concatenate([lane.present, np.zeros((num, 1), dtype=bool)], axis=1)
    positions[: len(far), -1], present[: len(far), -1] = far[:num], True
    rec = kit.scripted_recording([positions[present[:, j], j] for j in range(positions.shape[1])],
                                 [int(np.argmax(present[:, j])) for j in range(positions.shape[1])])  # fmt: skip
    trace = kit.simulate(model, rec, np.zeros(2))
    far_row = np.array([positions.shape[1] - 1])
    assert trace.robot_distance()[:, far_row].min() > ReactionParams().trigger_distance_m
    assert recorded_rows(trace, far_row)
    if model != "none":  # not vacuous: others did react
        assert trace.reacting.any()
        assert not recorded_rows(trace, np.arange(positions.shape[1] - 1))


def test_the_check_catches_a_pedestrian_moved_without_reason(kit) -> None:
    """The bit-for-bit check is sensitive: handing every pedestrian to ORCA (a trigger distance of 100 m) moves the
    far one by ORCA's single-precision rounding at least, and the check fails."""
    trace = kit.simulate(
        "orca",
        kit.head_on_recording(num=4),
        np.array([0.0, 40.0]),
        params=ReactionParams(trigger_distance_m=100.0, release_distance_m=100.0),
    )
    assert not recorded_rows(trace, np.arange(trace.positions.shape[1]))
