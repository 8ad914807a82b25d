"""``advance`` skips the steps in which nobody leaves the recording: the same crowd, bit for bit, as stepping."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from envs.reaction import REACTION_MODELS, make_reactive_crowd
from envs.reaction.base import ReactiveCrowd
from envs.replay import Replay


def robot_path(t: np.ndarray) -> np.ndarray:
    """A robot that waits far away, drives into the walkers' lane, stands in it a while, then leaves."""
    x = np.clip(-14.0 + 2.0 * (t - 2.0), -14.0, -2.0) + np.clip(t - 20.0, 0.0, None)
    return np.stack([x, 0.1 * np.sin(t)], axis=-1)


def run(model: str, quiet: bool, recording, substeps: int = 4, dt_s: float = 0.1) -> tuple[list, ReactiveCrowd, int]:
    replay = Replay(recording)
    crowd = make_reactive_crowd(model, robot_radius_m=0.3, pedestrian_radius_m=0.3)
    crowd.quiet_advance = quiet  # type: ignore[misc]
    skipped = 0
    original = crowd._quiet

    def counting(*args):
        nonlocal skipped
        out = original(*args)
        skipped += out is not None
        return out

    crowd._quiet = counting  # type: ignore[method-assign]
    crowd.reset(replay, replay.t_start_s)
    out = []
    t = replay.t_start_s
    for _ in range(70):
        times = t + dt_s * np.arange(substeps + 1)
        rec, present = replay.positions_at(times)
        robot = robot_path(times)
        seen = np.gradient(robot, dt_s, axis=0)[:-1]
        path = crowd.advance(t, dt_s, rec, present, robot, seen)
        state = getattr(crowd, "reacting", getattr(crowd, "shift_s", None))
        out.append((path, crowd.time_s, crowd.positions, crowd.present, state))
        t = crowd.time_s
    return out, crowd, skipped


@pytest.mark.parametrize("model", REACTION_MODELS)
def test_quiet_advance_equals_stepping(model: str, kit: SimpleNamespace) -> None:
    # walkers crossing the robot's line at different times, with wobbling (noisy) annotations: their recorded
    # velocity changes at every step, so a quiet stretch must leave the model's velocity state as stepping would
    tracks = [kit.line_recording((-9.0 + 1.5 * k, -6.0), (0.2, 1.2), 14.0, wobble_m=0.08) for k in range(8)]
    recording = kit.scripted_recording(tracks, [4 * k for k in range(8)], name="crossing")
    fast, _, skipped = run(model, True, recording)
    slow, _, never = run(model, False, recording)
    assert never == 0
    assert 0 < skipped < len(fast) or model == "none"  # both paths are exercised
    for k, (a, b) in enumerate(zip(fast, slow, strict=True)):
        pa, pb = a[0], b[0]
        for name in ("positions", "present"):
            np.testing.assert_array_equal(getattr(pa, name), getattr(pb, name), err_msg=f"{model} step {k} {name}")
        for name in ("positions", "velocities", "present", "reacting", "shift_s", "deviation_m", "offtrack_m"):
            np.testing.assert_array_equal(getattr(pa.last, name), getattr(pb.last, name), err_msg=f"{model} {k} {name}")
        assert a[1] == b[1]
        for x, y in zip(a[2:], b[2:], strict=True):
            np.testing.assert_array_equal(x, y)
    if model != "none":  # the robot did reach the walkers
        assert any(p.last.reacting.any() or p.last.shift_s.any() for p, *_ in slow)
