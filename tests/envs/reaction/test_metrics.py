"""Disturbance metrics: zero under ``none``, positive when people were disturbed, and the delay as defined (the
wait of a pausing pedestrian, the lag of one still behind its recording, nothing for one that caught up)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.reaction import REACTION_MODELS, DisturbanceMetrics, ReactionParams
from envs.reaction.metrics import nearest_time

TOL = ReactionParams().on_track_tolerance_m
CONTROL = 4  # substeps per control step: the metrics are updated at control steps, as the environment will


def measure(trace, upto: int | None = None) -> dict:
    """The metrics of a trace, updated every :data:`CONTROL` steps (up to row ``upto``)."""
    metrics = DisturbanceMetrics(TOL)
    last = len(trace.steps) if upto is None else upto
    for k in range(CONTROL - 1, last, CONTROL):
        metrics.update(trace.times[k + 1], trace.steps[k], trace.recorded[k + 1], trace.recorded_present[k + 1])
    return metrics.summary()


def test_none_disturbs_nobody(kit) -> None:
    summary = measure(kit.simulate("none", kit.head_on_recording(), np.zeros(2)))
    assert summary == {"ped_disturbed": 0, "ped_deviation_mean_m": 0.0, "ped_deviation_max_m": 0.0, "ped_delay_s": 0.0}


@pytest.mark.parametrize("model", [m for m in REACTION_MODELS if m != "none"])
def test_a_standing_robot_disturbs_people(kit, model: str) -> None:
    """The robot stands in the crowd's path until 20 s (the middle of the crowd has passed), then leaves."""
    trace = kit.simulate(model, kit.head_on_recording(), kit.moving_robot((0.0, 0.0), (0.0, 1.0), t0=20.0))
    summary = measure(trace)
    assert summary["ped_disturbed"] >= 5
    assert TOL < summary["ped_deviation_mean_m"] <= summary["ped_deviation_max_m"]
    if model == "pause":  # the delay is the time waited
        assert summary["ped_delay_s"] == pytest.approx(trace.shift[-1].sum())
        assert summary["ped_delay_s"] > 1.0
    else:  # every pedestrian caught up with its recording before its track ended: no delay, only the detour
        assert summary["ped_delay_s"] == 0.0


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_a_pedestrian_still_behind_its_recording_is_delayed(kit, model: str) -> None:
    """Stopped while the crowd is held up by the robot (at 15 s), the episode leaves pedestrians behind their
    recordings: their lags add up to a positive delay, no more than the time elapsed per pedestrian."""
    trace = kit.simulate(model, kit.head_on_recording(), np.zeros(2), seconds=15.0)
    summary = measure(trace)
    assert 0.0 < summary["ped_delay_s"] <= 15.0 * summary["ped_disturbed"]


def test_nearest_time_on_a_recorded_track() -> None:
    times = np.arange(6) * 0.4
    track = np.array([[0.0, 0.0], [0.4, 0.0], [0.8, 0.0], [0.8, 0.0], [0.8, 0.0], [1.2, 0.0]])
    present = np.ones(6, dtype=bool)
    assert nearest_time(np.array([0.2, 0.3]), times, track, present, 2.0) == pytest.approx(0.2)  # on a segment
    assert nearest_time(np.array([0.8, 0.0]), times, track, present, 2.0) == pytest.approx(1.6)  # standing: latest
    assert nearest_time(np.array([5.0, 0.0]), times, track, present, 1.0) == pytest.approx(0.8)  # not beyond t_max
    present[1] = False  # a gap: no segment across it
    assert nearest_time(np.array([0.2, 0.0]), times, track, present, 2.0) == pytest.approx(0.0)
    assert nearest_time(np.array([0.2, 0.0]), times, track, np.zeros(6, dtype=bool), 2.0) is None
