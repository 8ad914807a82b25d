"""``pause``: a pedestrian blocked by a standing robot waits before contact, then resumes its recording time-shifted
by the wait: its positions are a time-shifted copy of the recording."""

from __future__ import annotations

import numpy as np
import pytest

from envs.reaction import ReactionParams
from envs.replay import Replay

PARAMS = ReactionParams()


@pytest.fixture
def blocked(kit):
    """One pedestrian walking +x at 1.3 m/s from x = -5 m (10 s of track); the robot stands at the origin, on its
    path, until t = 6 s, then leaves along +y at 1 m/s."""
    rec = kit.scripted_recording([kit.line_recording((-5.0, 0.0), (1.3, 0.0), 10.0)])
    trace = kit.simulate("pause", rec, kit.moving_robot((0.0, 0.0), (0.0, 1.0), t0=6.0), seconds=14.0)
    return rec, trace


def shifted_copy_error(rec, trace) -> float:
    """Largest distance between the pedestrian and its recording at its own (shifted) time, over the run (presence
    must agree too: inf where it does not)."""
    replay = Replay(rec)
    shift = np.concatenate([[0.0], trace.shift[:, 0]])  # the shift at each row
    pos, present = replay.positions_at(trace.times - shift)
    if not np.array_equal(present[:, 0], trace.present[:, 0]):
        return float("inf")
    here = trace.present[:, 0]
    return float(np.abs(pos[here, 0] - trace.positions[here, 0]).max())


def test_a_blocked_pedestrian_waits_before_contact_then_resumes_time_shifted(kit, blocked) -> None:
    rec, trace = blocked
    waits = trace.reacting[:, 0]
    assert waits.any()
    # it stands still while it waits, never closer than the contact distance plus the margin
    k = np.flatnonzero(waits)
    assert np.array_equal(trace.positions[k + 1, 0], trace.positions[k, 0])
    assert trace.robot_distance()[:, 0].min() >= kit.contact_m + PARAMS.pause_margin_m - 1e-9
    # the shift is the time waited, and stays once the robot has gone
    assert trace.shift[-1, 0] == pytest.approx(waits.sum() * kit.dt_s, abs=1e-9)
    assert np.all(np.diff(trace.shift[:, 0]) >= 0.0)
    assert not waits[int(7.0 / kit.dt_s) :].any()
    # everywhere, it is its recording at its own clock (a time-shifted copy), present as long as that is
    assert shifted_copy_error(rec, trace) <= 1e-9
    # its track ends (10 s) that much later than recorded
    last = trace.times[np.flatnonzero(trace.present[:, 0])[-1]]
    assert last == pytest.approx(10.0 + trace.shift[-1, 0], abs=kit.dt_s / 2)


def test_the_check_catches_a_pedestrian_that_resumes_unshifted(kit, blocked, monkeypatch) -> None:
    """A broken pause that forgets the wait (resumes where the recording is now, i.e. jumps) fails the copy check."""
    import envs.reaction.pause as pause

    rec, _ = blocked
    real = pause.PausingCrowd._step

    def forgetful(self, *args):
        out = real(self, *args)
        self._shift[:] = 0.0  # the wait is forgotten
        return out

    monkeypatch.setattr(pause.PausingCrowd, "_step", forgetful)
    trace = kit.simulate("pause", rec, kit.moving_robot((0.0, 0.0), (0.0, 1.0), t0=6.0), seconds=14.0)
    assert shifted_copy_error(rec, trace) > 0.5
