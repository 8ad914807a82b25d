"""``social_force``: replay-then-model with the social-force model of the project's synthetic crowd.

The force law is the one :func:`envs.recordings.synthetic_recording` integrates (Helbing & Molnár's exponential
form with an anisotropic weight): a reacting pedestrian ``i`` walking in direction ``e_i`` (its preferred velocity's)
accelerates by

    (v_pref - v) / tau  +  sum_j A exp((d_c - d_ij) / B) w(phi_ij) n_ij,    w = lambda + (1 - lambda)(1 + cos phi) / 2,

``n_ij`` the unit vector from ``j`` to ``i``, ``cos phi_ij = -n_ij . e_i``, ``d_c = pair_distance_m``.

**The robot** is a hard body that does not give way and may move fast: it repels through Helbing & Molnár's
(1995) elliptical potential, ``U0 exp(-(b - r_robot) / R)``, ``2b = sqrt((|d| + |d - s|)² - |s|²)``, ``d`` from
the robot to the pedestrian, ``s = v_robot * sf_robot_step_s`` the robot's step (their Δt = 2 s), with the strength
and range of their borders (U0 = 10 m²/s², R = 0.2 m: about 11 m/s² at contact with a standing robot), weighted by
``w(phi)``. Measured on 20 walkers at 1.3 m/s head-on (``tests/envs/reaction/test_avoidance.py``): with the
pedestrians' own constants (A = 2 m/s², B = 0.3 m, circular) they reach 0.34 m of a standing robot's centre
(contact: 0.6 m), because 2 m/s² at contact is less than the pull of their preferred velocity (2.6 m/s²); with a
circular border potential they keep 0.70 m from a standing robot, but a robot driving at them at 1 m/s reaches
0.39 m; the ellipse keeps both (0.70 m and 1.16 m).

Integrated with one explicit Euler step per model step, then bounded (:mod:`envs.reaction.steered`). The step
starts from the pedestrian's velocity plus the change of its recorded velocity over the step (``v + Δv_rec``): the
relaxation then acts on the deviation from the recording only, so a reacting pedestrian on its track with no force on
it walks exactly as recorded (as under ``orca``). Without that term (revision 1 of the model) the relaxation lagged
each recorded change of velocity by ``tau``, and a triggered pedestrian drifted off its track with no force at all
(``benchmarks/disturbance_sources.py``; docs/reaction.md).

**Pedestrians among pedestrians.** The recording already holds how these people kept their distances; a static
repulsion from every neighbour would push recorded groups apart as soon as one member reacts. So between
pedestrians only the *change* acts: the force of ``j`` on ``i`` is the force at their actual positions minus the
force at their recorded positions now (zero while both are where the recording has them). The robot, absent from
the recording, acts in full.

Why this and not pysocialforce: the project already carries this force law and its constants (the synthetic
crowd), the model needs a few vectorised lines over the reacting pedestrians only, and pysocialforce (not installed)
integrates whole scenes of goal-seeking agents with its own state, obstacles and group forces, which would have to
be bypassed to feed recorded neighbours and a robot moving as it does. The synthetic crowd integrates its law inline;
in the second phase it can call :func:`repulsion` instead.
"""

from __future__ import annotations

import numpy as np

from envs.reaction.steered import Neighbourhood, SteeredCrowd


def repulsion(diff: np.ndarray, directions: np.ndarray, contact_m: float, a: float, b: float, lam: float) -> np.ndarray:
    """The anisotropic exponential repulsion ``A exp((d_c - d) / B) w(phi) n`` on pedestrians, summed over sources.

    Args:
        diff: ``(..., m, k, 2)`` each pedestrian's position minus each source's, metres (a zero row, a source on the
            pedestrian itself, exerts nothing); leading axes: several configurations at once.
        directions: ``(m, 2)`` the pedestrians' unit walking directions.
        contact_m: distance at which the force is ``a`` (times the weight), metres.
        a: strength A, m/s².
        b: range B, metres.
        lam: anisotropy λ.

    Returns:
        ``(..., m, 2)`` accelerations, m/s² (each configuration's the floats it has alone: the arithmetic is element by
        element and each pedestrian's sum runs along the last, contiguous axis).
    """
    dx, dy = diff[..., 0], diff[..., 1]
    d = np.hypot(dx, dy)
    inv = np.where(d > 1e-9, 1.0 / np.maximum(d, 1e-9), 0.0)
    cos_phi = -(dx * directions[:, None, 0] + dy * directions[:, None, 1]) * inv
    mag = a * np.exp((contact_m - d) / b) * (lam + (1.0 - lam) * (1.0 + cos_phi) / 2.0) * inv
    return np.stack([(mag * dx).sum(axis=-1), (mag * dy).sum(axis=-1)], axis=-1)


def robot_repulsion(
    positions: np.ndarray,
    directions: np.ndarray,
    robot: np.ndarray,
    step: np.ndarray,
    radius_m: float,
    u0: float,
    r0: float,
    lam: float,
) -> np.ndarray:
    """The robot's push on each pedestrian: minus the gradient of Helbing & Molnár's elliptical potential.

    Args:
        positions: ``(m, 2)`` pedestrians, metres.
        directions: ``(m, 2)`` their unit walking directions.
        robot: ``(2,)`` the robot's centre, metres.
        step: ``(2,)`` the robot's step ``v * dt`` (its position ``dt`` ahead minus now), metres.
        radius_m: the robot's radius, metres.
        u0: strength U0, m²/s².
        r0: range R, metres.
        lam: anisotropy λ.

    Returns:
        ``(m, 2)`` accelerations, m/s².
    """
    d = positions - robot[None, :]
    a = np.hypot(d[:, 0], d[:, 1])
    ds = d - step[None, :]
    c = np.hypot(ds[:, 0], ds[:, 1])
    ac = a + c
    b = 0.5 * np.sqrt(np.maximum(ac**2 - float(step @ step), 0.0))
    # grad b = (a + c) (d / a + (d - s) / c) / (4 b); the force is (V / R) grad b
    n = d / np.maximum(a, 1e-9)[:, None]
    grad_b = (ac / np.maximum(4.0 * b, 1e-9))[:, None] * (n + ds / np.maximum(c, 1e-9)[:, None])
    mag = u0 / r0 * np.exp(-(b - radius_m) / r0)
    weight = lam + (1.0 - lam) * (1.0 - np.einsum("mc,mc->m", n, directions)) / 2.0
    return (mag * weight)[:, None] * grad_b


class SocialForceCrowd(SteeredCrowd):
    """``social_force`` (see the module docstring and :mod:`envs.reaction.steered`)."""

    name = "social_force"

    def _model_velocities(self, hood: Neighbourhood) -> np.ndarray:
        prm = self.params
        a, b, lam, pair = prm.sf_repulsion_mps2, prm.sf_range_m, prm.sf_anisotropy, prm.pair_distance_m
        p = hood.positions
        v = hood.velocities + hood.recorded_change  # carried along with the recording's own change of velocity
        speed = np.hypot(hood.preferred[:, 0], hood.preferred[:, 1])
        e = hood.preferred / np.maximum(speed, 1e-9)[:, None]
        force = (hood.preferred - v) / prm.sf_relaxation_time_s
        force += robot_repulsion(
            p,
            e,
            hood.robot,
            hood.robot_velocity * prm.sf_robot_step_s,
            self.robot_radius_m,
            prm.sf_robot_potential_m2ps2,
            prm.sf_robot_range_m,
            lam,
        )
        # between pedestrians, the change from the recorded configuration: sources are the reacting pedestrians
        # (themselves excluded: a zero difference) and their non-reacting neighbours, actual minus recorded
        actual = np.concatenate([p, hood.other_positions])
        if len(actual) > 1:  # both configurations in one call
            recorded = np.concatenate([hood.recorded, hood.other_positions])
            sources = np.stack([actual, recorded])[:, None, :, :]
            push = repulsion(np.stack([p, hood.recorded])[:, :, None, :] - sources, e, pair, a, b, lam)
            force += push[0]
            force -= push[1]
        return v + force * hood.dt_s
