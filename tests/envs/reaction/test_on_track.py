"""A reacting pedestrian with nothing to avoid walks exactly as recorded, even where its recorded velocity changes
(the preferred velocity is the recorded one on the track; the model must not lag behind it)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.reaction import ReactionParams
from envs.reaction.social_force import SocialForceCrowd

#: social force with the robot's push switched off: the robot triggers the pedestrian and exerts nothing.
NO_PUSH = ReactionParams(sf_robot_potential_m2ps2=0.0)


def circling(radius_m: float = 2.5, speed_mps: float = 1.0, seconds: float = 12.0) -> np.ndarray:
    """Annotations (every 0.4 s) of a walk around the origin at ``radius_m``: its velocity turns at every
    annotation (by 0.16 m/s at the defaults, within the 0.2 m/s a substep allows)."""
    t = 0.4 * np.arange(int(seconds / 0.4) + 1)
    angle = speed_mps * t / radius_m
    return radius_m * np.stack([np.cos(angle), np.sin(angle)], axis=1)


@pytest.mark.parametrize(("model", "params"), [("social_force", NO_PUSH), ("orca", None)])
def test_a_reacting_pedestrian_on_its_track_follows_a_turning_recording(kit, model: str, params) -> None:
    """Around a robot standing 2.5 m away (inside the trigger distance, never on a collision course): the pedestrian
    reacts the whole time and is where its recording has it at every substep (within a micron)."""
    trace = kit.simulate(model, kit.scripted_recording([circling()], [0], name="circling"), np.zeros(2), params=params)
    assert trace.reacting[:-1, 0].all()
    off = np.hypot(*(trace.positions[:, 0] - trace.recorded[:, 0]).T)
    assert off.max() < 1e-6, f"{model}: {off.max():.3g} m off the recording"  # RVO2 rounds to ~1e-8 m


def test_the_check_catches_a_lagging_relaxation(kit, monkeypatch: pytest.MonkeyPatch) -> None:
    """Social force's revision 1 (relaxing towards the preferred velocity from the velocity before, without the
    recording's own change) drifts centimetres off the turning track with no force on it."""
    relax = SocialForceCrowd._model_velocities

    def lagging(self, hood):
        hood.recorded_change = np.zeros_like(hood.recorded_change)
        return relax(self, hood)

    monkeypatch.setattr(SocialForceCrowd, "_model_velocities", lagging)
    trace = kit.simulate(
        "social_force", kit.scripted_recording([circling()], [0], name="c"), np.zeros(2), params=NO_PUSH
    )
    assert np.hypot(*(trace.positions[:, 0] - trace.recorded[:, 0]).T).max() > 0.01
