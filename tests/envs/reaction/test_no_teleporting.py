"""Rule 2: reacting pedestrians move with bounded speed and acceleration, and rejoin their recording continuously
(no step longer than the speed bound allows) once the robot has left."""

from __future__ import annotations

import numpy as np
import pytest

import envs.reaction.steered as steered
from envs.reaction import ReactionParams

PARAMS = ReactionParams()


def scene(kit, model: str, params: ReactionParams | None = None):
    """A crowd walking head-on at a robot that drives at them at 1 m/s for 4 s, stands until 9 s, then leaves
    sideways at 1 m/s; 26 s in all, until the last pedestrian's track has ended."""
    leave = kit.moving_robot((0.0, 0.0), (0.0, 1.0), t0=9.0)

    def robot(t: float) -> tuple[np.ndarray, np.ndarray]:
        if t < 4.0:
            return np.array([4.0 - t, 0.0]), np.array([-1.0, 0.0])
        return leave(t)

    return kit.simulate(model, kit.head_on_recording(num=12, gap_steps=2), robot, seconds=26.0, params=params)


def bound_violations(trace, params: ReactionParams) -> dict[str, float]:
    """The largest excess over each bound in the steps the model was in charge of (reacting at the step's start or
    end; the pedestrian present at both ends and one step before, so its previous velocity is its own).

    Returns:
        ``{"speed": m/s, "accel": m/s², "step": m}``, each 0 when the bound holds.
    """
    dt = trace.dt_s
    v = trace.velocities  # (K, N, 2)
    speed = np.hypot(v[..., 0], v[..., 1])
    prev_speed = np.vstack([speed[:1], speed[:-1]])
    accel = np.hypot(*(np.diff(v, axis=0) / dt).transpose(2, 0, 1))  # (K - 1, N): step k + 1 against step k
    pres = trace.present
    own = trace.reacted[1:] & pres[:-2] & pres[1:-1] & pres[2:]
    step = np.hypot(*np.diff(trace.positions, axis=0).transpose(2, 0, 1))[1:]
    cap = np.maximum(params.max_speed_mps, prev_speed[1:])
    return {
        "speed": float(np.max(np.where(own, speed[1:] - cap, 0.0), initial=0.0)),
        "accel": float(np.max(np.where(own, accel - params.max_accel_mps2, 0.0), initial=0.0)),
        "step": float(np.max(np.where(own, step - params.max_speed_mps * dt, 0.0), initial=0.0)),
    }


def rejoined(trace) -> bool:
    """Every pedestrian that reacted was handed back to its recording before its track ended: at its last step it is
    not reacting and is exactly (bit for bit) at its recorded position."""
    for j in np.flatnonzero(trace.reacted.any(axis=0)).tolist():
        last = int(np.flatnonzero(trace.present[:, j])[-1])  # its last row
        if trace.reacting[last - 1, j] or not np.array_equal(trace.positions[last, j], trace.recorded[last, j]):
            return False
    return True


def gradual(trace, tolerance_m: float) -> bool:
    """Before each hand-back, the deviation from the recording shrinks step by step (5 steps) to within twice the
    tolerance (the landing is decided on where the model would put the pedestrian: within the tolerance)."""
    for j in np.flatnonzero(trace.reacted.any(axis=0)).tolist():
        dev = np.hypot(*(trace.positions[:, j] - trace.recorded[:, j]).T)
        if dev[trace.present[:, j]].max() <= tolerance_m:
            continue  # never really off its track
        k = int(np.flatnonzero(trace.reacted[:, j])[-1])  # the landing step: rows k -> k + 1
        before = dev[k - 4 : k + 1]
        if np.any(np.diff(before) > 1e-6) or before[-1] > 2 * tolerance_m:
            return False
    return True


#: Bounds tight enough to bind in the scene: the social force's pedestrians, held up by the robot, catch up with
#: their recordings (1.3 m/s) at more than 1.5 m/s (ORCA's sidestep and never need more than 1.36 m/s here).
TIGHT = ReactionParams(max_speed_mps=1.5, max_accel_mps2=1.0)


@pytest.mark.parametrize("params", [PARAMS, TIGHT], ids=["defaults", "tight"])
@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_reacting_pedestrians_keep_the_bounds_and_rejoin(kit, model: str, params: ReactionParams) -> None:
    trace = scene(kit, model, params)
    assert trace.reacted.any(axis=0).sum() >= 8  # not vacuous: most of the crowd reacted
    excess = bound_violations(trace, params)
    assert all(x <= 1e-9 for x in excess.values()), excess
    assert rejoined(trace)
    assert gradual(trace, params.on_track_tolerance_m)
    if params is TIGHT and model == "social_force":  # the bound did bind: someone walked at the speed bound
        speed = np.hypot(*trace.velocities.transpose(2, 0, 1))
        assert speed[trace.reacted].max() == pytest.approx(params.max_speed_mps)


def test_the_checks_catch_an_unbounded_model(kit, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the bounds (the model's velocity taken as it is), the bound check fails."""
    monkeypatch.setattr(steered, "_bounded", lambda v, v0, max_change, speed_cap: v)
    assert bound_violations(scene(kit, "orca"), PARAMS)["accel"] > 1.0


def test_the_checks_catch_a_model_that_never_rejoins(kit) -> None:
    """A model that never hands pedestrians back (a release distance beyond reach) fails the rejoin check."""
    assert not rejoined(scene(kit, "orca", ReactionParams(release_distance_m=1e6)))


def test_a_pedestrian_triggered_faster_than_the_bound_only_slows_down(kit) -> None:
    """A recorded runner at 3 m/s (above the 2.5 m/s bound) meets a standing robot: while reacting, its speed never
    exceeds its speed one step before, nor its acceleration the bound."""
    rec = kit.scripted_recording([kit.line_recording((-9.0, 0.4), (3.0, 0.0), 8.0)])
    trace = kit.simulate("orca", rec, np.zeros(2))
    assert trace.reacted.any()
    assert bound_violations(trace, PARAMS)["accel"] <= 1e-9
    own = trace.reacted[1:, 0]
    speed = np.hypot(*trace.velocities[:, 0].T)
    assert np.all(speed[1:][own] <= np.maximum(PARAMS.max_speed_mps, speed[:-1][own]) + 1e-12)
