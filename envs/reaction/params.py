"""Parameters of the reaction models, each with its unit in the name and the source or reason of its default.

One frozen dataclass, :class:`ReactionParams`, holds every constant of every model (``pause``, ``orca``,
``social_force``); ``none`` uses none of them. :meth:`ReactionParams.to_dict` is what goes into the environment's
revision and every cell's spec; :meth:`ReactionParams.from_mapping` merges overrides onto the defaults, rejecting an
unknown key with the valid ones and a bad value with the key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from crowdnav_mesrnn.config import ConfigError, replace_checked

#: Names of the reaction models, ``reaction=`` in the environment's configuration.
REACTION_MODELS: Final[tuple[str, ...]] = ("none", "pause", "orca", "social_force")

#: Revision of each model's dynamics, bumped whenever the same episode and parameters can move someone otherwise;
#: named in the rules' identity (``envs.crowd_nav.env_rules``, every cell's spec, the reset ``info``) from 2 on, so
#: results of revision 1 of the other models stay valid. ``social_force`` 2: the relaxation acts on the deviation from
#: the recording (``envs.reaction.social_force``); revision 1 lagged every recorded change of velocity.
MODEL_REVISIONS: Final[dict[str, int]] = {"none": 1, "pause": 1, "orca": 1, "social_force": 2}


def revision_rules(model: str) -> dict[str, int]:
    """``{"reaction_revision": n}`` for a model at revision ``n >= 2`` (:data:`MODEL_REVISIONS`), else ``{}``."""
    revision = MODEL_REVISIONS[model]
    return {"reaction_revision": revision} if revision != 1 else {}


@dataclass(frozen=True)
class ReactionParams:
    """Constants of the reaction models (see ``docs/reaction.md`` for the model they parametrise).

    The contact distance between the robot and a pedestrian is not here: it is the environment's
    ``robot_radius_m + pedestrian_radius_m`` (one source of truth), passed to the crowd when it is made.
    """

    # --- when a pedestrian reacts (orca, social_force)
    trigger_distance_m: float = 3.0
    """A pedestrian starts to react when the robot's centre comes closer than this to its own, metres. Reason: the
    far edge of Hall's (1966) social zone (1.2-3.7 m), within which people attend to those around them; and long
    enough to avoid a head-on robot: at a closing speed of 2.3 m/s (a 1.3 m/s walker, the robot's 1 m/s) it leaves
    1.0 s, in which a 2 m/s² lateral acceleration moves a pedestrian 1 m > the 0.6 m contact distance."""
    release_distance_m: float = 3.5
    """A reacting pedestrian may return to its recording only once the robot is farther than this, metres.
    Hysteresis of 0.5 m over ``trigger_distance_m``, so a robot hovering at the trigger distance does not switch a
    pedestrian in and out of the model at every step."""
    on_track_tolerance_m: float = 0.01
    """A pedestrian within this distance of its recorded position is *on its recording*, metres: it returns to the
    recording (only) when it can land exactly on it within the speed and acceleration bounds from this close
    (so there is no visible jump), and it counts as *disturbed* once it has been farther. 1 cm: below the
    annotation noise of ETH/UCY positions (several cm), so a pedestrian never looks displaced by the switch."""
    lookahead_s: float = 1.0
    """A reacting pedestrian's preferred velocity points at where its recording would be this long ahead at its
    recorded velocity, seconds: ``v_pref = v_rec + (p_rec - p) / lookahead_s``. Off its track, the deviation
    decays with this time constant (1 m to 1 cm in about 4.6 s); on it, the pedestrian walks exactly as recorded.
    About two walking steps (cadence ~2 steps/s): a gradual return to one's line, not a sharp turn."""

    # --- bounds of a reacting pedestrian's motion (orca, social_force)
    max_speed_mps: float = 2.5
    """Speed bound of a reacting pedestrian, m/s (also the cap of its preferred speed, so the fastest catch-up
    with its recording). Bohannon (1997, Age Ageing 26:15-19): maximum gait speed 1.75-2.53 m/s over adults aged
    20-79 (2.53 m/s for men in their twenties); ETH/UCY annotation-rate speeds
    (this project's recordings) have their 99th percentile at 1.6-2.2 m/s per scene, and the few faster
    pedestrians keep their recorded speed until they are triggered, then only slow down."""
    max_accel_mps2: float = 2.0
    """Acceleration bound of a reacting pedestrian, m/s². ETH/UCY annotation-rate accelerations (this project's
    recordings) have their 99th percentile at 1.1-1.8 m/s² per scene; Helbing & Molnár's (1995) relaxation time
    of 0.5 s turns a 1 m/s change of velocity into the same 2 m/s²."""

    # --- between pedestrians (orca, social_force)
    pair_distance_m: float = 0.3
    """Centre distance two pedestrians keep from each other in the models, metres (ORCA's combined radius of two
    pedestrians; the social force's contact distance). Not the environment's 0.6 m robot-contact distance:
    ETH/UCY neighbours are annotated closer than 0.6 m in 5-46 % of cases (students001: 46 %), which a 0.6 m
    pair distance would turn into pushing. 0.3 m is the 5th percentile of nearest-neighbour distances in the
    densest recording (students001), so 95 % of recorded neighbours never touch."""
    neighbor_distance_m: float = 10.0
    """Pedestrians (and the robot) within this centre distance of a reacting pedestrian are its neighbours in the
    models, metres. CrowdNav's ORCA setting (Chen et al. 2019, ``neighbor_dist = 10``)."""

    # --- ORCA (pyrvo, the RVO2 library)
    orca_time_horizon_s: float = 3.0
    """ORCA's time horizon: a reacting pedestrian avoids collisions predicted within this time, seconds.
    Karamouzas, Skinner & Guy (2014, Phys. Rev. Lett. 113, 238701): pedestrians' interaction energy falls with the
    time to collision and vanishes beyond about 3 s. (CrowdNav uses 5 s for its synthetic crowds.)"""
    orca_max_neighbors: int = 10
    """ORCA considers at most this many nearest neighbours. CrowdNav's ORCA setting (``max_neighbors = 10``)."""

    # --- social force (the project's synthetic crowd: Helbing & Molnár's exponential form)
    sf_relaxation_time_s: float = 0.5
    """Relaxation time towards the preferred velocity, seconds. Helbing & Molnár (1995), as the project's synthetic
    crowd (:func:`envs.recordings.synthetic_recording`)."""
    sf_repulsion_mps2: float = 2.0
    """Strength A of the repulsion between pedestrians ``A exp((d_contact - d) / B)``, m/s². The project's synthetic
    crowd (Helbing & Molnár's exponential form; their potential V0 = 2.1 m²/s²)."""
    sf_range_m: float = 0.3
    """Range B of the repulsion between pedestrians, metres. Helbing & Molnár (1995, σ = 0.3 m), as the project's synthetic crowd."""
    sf_robot_potential_m2ps2: float = 10.0
    """Strength U0 of the robot's repulsive potential ``U0 exp(-(b - r_robot) / R)``, m²/s², ``b`` the semi-minor axis
    of Helbing & Molnár's ellipse (the centre distance for a standing robot; force ``U0 / R`` at the robot's surface).
    The robot is a hard body that does not give way, so it repels with the strength of Helbing & Molnár's (1995)
    borders (U0 = 10 m²/s²), not a pedestrian's (2.1 m²/s²)."""
    sf_robot_range_m: float = 0.2
    """Range R of the robot's repulsive potential, metres. Helbing & Molnár (1995), borders (R = 0.2 m)."""
    sf_robot_step_s: float = 2.0
    """The robot's repulsion is stretched along its motion: its equipotential lines are Helbing & Molnár's (1995)
    ellipses through the robot and its position this long ahead (their Δt = 2 s), seconds. 0 makes it circular,
    which lets a robot driving head-on at 1 m/s into 1.3 m/s walkers reach 0.39 m of their centres (contact:
    0.6 m); with 2 s they keep 1.16 m (``tests/envs/reaction/test_avoidance.py``)."""
    sf_anisotropy: float = 0.35
    """Weight λ of what is behind a pedestrian (1: isotropic): the force is multiplied by
    ``λ + (1 - λ)(1 + cos φ) / 2``, φ between the walking direction and the other. The project's synthetic crowd."""

    # --- pause (SocNavBench's rule)
    pause_margin_m: float = 0.1
    """A pausing pedestrian waits while its next position would be closer to the robot than the contact distance
    plus this gap, metres. The environment's pop-in margin (``envs.popin.POPIN_MARGIN_M``, the gap at which a
    pedestrian counts as clear of the robot); it also covers the robot's own motion during a 0.1 s substep."""

    def __post_init__(self) -> None:
        for key, (lo, lo_open, integer) in _BOUNDS.items():
            _check(key, getattr(self, key), lo, lo_open, integer)
        if self.release_distance_m < self.trigger_distance_m:
            raise ConfigError(
                f"reaction parameter 'release_distance_m' = {self.release_distance_m!r} must be >= "
                f"'trigger_distance_m' = {self.trigger_distance_m!r} (the release distance is the trigger distance "
                "plus a hysteresis)"
            )

    def to_dict(self) -> dict[str, Any]:
        """Every parameter by name (plain floats and ints), for the environment's revision and cells' specs."""
        return dataclasses.asdict(self)

    @classmethod
    def from_mapping(cls, overrides: Mapping[str, Any] | None = None) -> ReactionParams:
        """The defaults with ``overrides`` applied; :class:`~crowdnav_mesrnn.config.ConfigError` for an unknown key
        (listing the valid ones) or a bad value (naming the key, the value and what is allowed)."""
        if overrides is not None and not isinstance(overrides, Mapping):
            raise ConfigError(
                f"reaction_params (the reaction parameters) must be a mapping, got {type(overrides).__name__}: {overrides!r}"
            )
        return replace_checked(cls(), overrides, where="reaction parameter")


#: Lower bound of each parameter: (bound, open, integer). None is unbounded; every value must be finite.
_BOUNDS: Final[dict[str, tuple[float, bool, bool]]] = {
    "trigger_distance_m": (0.0, True, False),
    "release_distance_m": (0.0, True, False),
    "on_track_tolerance_m": (0.0, True, False),
    "lookahead_s": (0.0, True, False),
    "max_speed_mps": (0.0, True, False),
    "max_accel_mps2": (0.0, True, False),
    "pair_distance_m": (0.0, False, False),
    "neighbor_distance_m": (0.0, True, False),
    "orca_time_horizon_s": (0.0, True, False),
    "orca_max_neighbors": (1.0, False, True),
    "sf_relaxation_time_s": (0.0, True, False),
    "sf_repulsion_mps2": (0.0, False, False),
    "sf_range_m": (0.0, True, False),
    "sf_robot_potential_m2ps2": (0.0, False, False),
    "sf_robot_range_m": (0.0, True, False),
    "sf_robot_step_s": (0.0, False, False),
    "sf_anisotropy": (0.0, False, False),
    "pause_margin_m": (0.0, False, False),
}


def _check(key: str, value: Any, lo: float, lo_open: bool, integer: bool) -> None:
    """Raise :class:`ConfigError` naming ``key``, ``value`` and the allowed range unless ``value`` fits."""
    allowed = f"{'an integer' if integer else 'a finite number'} {'>' if lo_open else '>='} {lo:g}"
    if key == "sf_anisotropy":
        allowed = "a number in [0, 1]"
    real = isinstance(value, int | float) and not isinstance(value, bool)
    ok = real and math.isfinite(value) and (value > lo if lo_open else value >= lo)
    if integer:
        ok = ok and isinstance(value, int)
    if key == "sf_anisotropy":
        ok = ok and value <= 1.0
    if not ok:
        raise ConfigError(f"reaction parameter {key!r} must be {allowed}, got {value!r}")


def check_model(name: Any) -> str:
    """``name`` if it is one of :data:`REACTION_MODELS`, else :class:`ConfigError` listing them."""
    if isinstance(name, str) and name in REACTION_MODELS:
        return name
    raise ConfigError(f"unknown reaction {name!r}; valid: {', '.join(REACTION_MODELS)}")
