"""Configuration of the crowd-navigation environment: defaults in code, overrides from mappings or YAML.

Every setting is a field of :class:`CrowdNavConfig` with its unit in the name where it matters.
``CrowdNavEnv(config=..., **kwargs)`` merges a mapping (or a YAML file) and keyword arguments onto
the defaults with :func:`crowdnav_mesrnn.config.replace_checked`: an unknown key is a
:class:`~crowdnav_mesrnn.config.ConfigError` listing the valid ones, and :meth:`CrowdNavConfig.validate`
rejects bad values (an unknown split, part, scene, crowd, predictor or kinematics lists the valid values).
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, check_keys, load_yaml, replace_checked
from crowdnav_mesrnn.data.constants import RECORDINGS, SPLIT_TEST_RECORDINGS, SPLITS
from crowdnav_mesrnn.data.paths import DataNotFoundError, find_data_dir
from envs.reaction.params import ReactionParams, check_model

#: Crowd sources accepted by ``crowd=`` (or a :class:`~crowdnav_mesrnn.data.Recording` object).
CROWDS: Final[tuple[str, ...]] = ("auto", "replay", "synthetic", "empty")
#: Keys that name ETH/UCY scenes: given (in a config or as keywords), ``crowd="auto"`` needs the data.
SCENE_KEYS: Final[tuple[str, ...]] = ("split", "part", "scenes")
#: Which recordings an episode may replay: ``test`` = the split's held-out scene, ``train`` = the other four.
EPISODE_PARTS: Final[tuple[str, ...]] = ("train", "test")
KINEMATICS: Final[tuple[str, ...]] = ("holonomic", "unicycle")
#: How learned forecasts remember the past (``forecast_memory=``); ``window`` is the evaluated protocol.
FORECAST_MEMORIES: Final[tuple[str, ...]] = ("window", "carried")
#: Which part of each recording's duration episodes lie in (``episode_time=``): ``val`` = the last
#: ``val_fraction``, ``train`` = before it, ``all`` = anywhere.
EPISODE_TIMES: Final[tuple[str, ...]] = ("all", "train", "val")
#: How the ``forecast_uncertainty`` thresholds are set (``forecast_uncertainty_method=``); ``split`` is the default.
UNCERTAINTY_METHODS: Final[tuple[str, ...]] = ("split", "online")


@dataclass(frozen=True)
class CrowdNavConfig:
    """Every setting of :class:`envs.crowd_nav.CrowdNavEnv` (defaults here; ``configs/env/default.yaml`` mirrors them)."""

    # ----------------------------------------------------------------- crowd and episodes
    split: str = "zara1"
    """Leave-one-out split (``eth``, ``hotel``, ``univ``, ``zara1``, ``zara2``) choosing the recordings."""
    part: str = "train"
    """``test``: episodes replay the split's held-out scene; ``train``: the other four scenes' recordings."""
    scenes: tuple[str, ...] = ()
    """Restrict episodes to these recordings (``crowds_zara01``) or scene labels (``zara1``, ``univ``); empty = all of the part."""
    crowd: str = "auto"
    """``replay`` (ETH/UCY), ``synthetic`` (social-force crowd), ``empty``, or ``auto``: replay when the data is
    found; without it, an error when a scene is named (``split``, ``part`` or ``scenes`` given, or ``data_dir``),
    else the embedded default, the synthetic crowd, with a warning (see :func:`crowd_source`)."""
    data_dir: str | None = None
    """ETH/UCY folder; default: ``$CROWDNAV_MESRNN_DATA``, ``./data/eth_ucy``, ``~/.cache/crowdnav-mesrnn/eth_ucy``."""
    predictor: str = "mesrnn"
    """Forecast source: ``none``, ``cv``, ``mesrnn``, ``srnn``, ``vlstm``, ``oracle``, ``noisy_oracle``, an installed
    predictor plug-in's name or an import path ``package.module:Factory`` (or pass a predictor object)."""

    # ----------------------------------------------------------------- pedestrians' reaction to the robot
    reaction: str = "none"
    """How pedestrians react to the robot (:data:`envs.reaction.REACTION_MODELS`): ``none`` (the recording, exactly:
    nobody sees the robot), ``pause`` (wait before contact, then resume the recording time-shifted by the wait),
    ``orca`` or ``social_force`` (replay-then-model: follow the recording until the robot comes within
    ``reaction_params["trigger_distance_m"]``, react through the model, rejoin the recording). A model of reaction,
    not measured people; the ``oracle`` forecast stays the recording, what a person would have done without the
    robot. See ``docs/reaction.md``."""
    reaction_params: dict[str, Any] = field(default_factory=lambda: ReactionParams().to_dict())
    """Constants of the reaction models (:class:`envs.reaction.ReactionParams`, each with its unit and the source of
    its default): a mapping of overrides, e.g. ``{"trigger_distance_m": 2.0}``, merged onto the defaults (the
    config holds them all, resolved). ``none`` uses none of them."""

    # ----------------------------------------------------------------- robot and physics
    kinematics: str = "holonomic"
    """``holonomic`` (action = velocity) or ``unicycle`` (action = speed, turn rate)."""
    robot_radius_m: float = 0.3
    """Robot disk radius, metres."""
    robot_pref_speed_mps: float = 1.0
    """Preferred (= maximum) robot speed, m/s; the action is scaled by it."""
    robot_max_turn_rate_radps: float = 2.0
    """Unicycle: maximum turn rate, rad/s (action[1] = ±1)."""
    pedestrian_radius_m: float = 0.3
    """Pedestrian disk radius, metres."""
    dt_s: float = 0.4
    """Control step, seconds (the data's annotation step)."""
    physics_dt_s: float = 0.1
    """Longest physics substep, seconds (substeps per control step = ceil(dt_s / physics_dt_s))."""

    # ----------------------------------------------------------------- episodes
    start_goal_distance_m: tuple[float, float] = (6.0, 12.0)
    """Range of the straight-line start-goal distance, metres."""
    start_clearance_m: float = 1.0
    """Minimum gap (surface to surface) between the robot's start and every pedestrian at t0, metres."""
    time_limit_factor: float = 3.0
    """Time limit = factor x straight-line distance / preferred speed."""
    goal_tolerance_m: float = 0.3
    """The goal is reached when the robot's centre is this close to it, metres."""
    terminate_on_collision: bool = True
    """End the episode at the first robot-pedestrian contact (False: keep running, penalise every step in contact)."""
    require_pedestrians: bool = False
    """Resample episodes until at least one pedestrian comes within ``sensor_range_m`` of the straight start-goal
    segment during the episode (at annotation times); deterministic per seed and identical in every forecast arm."""
    episode_time: str = "all"
    """Where episodes lie in each recording's duration: ``all`` (anywhere), ``train`` (wholly before the last
    ``val_fraction``) or ``val`` (wholly inside the last ``val_fraction``), for validating agents on unseen times."""
    val_fraction: float = 0.2
    """Share of each recording's duration (its end) reserved for ``episode_time="val"`` episodes, in (0, 1)."""
    crowd_overlays: int = 0
    """Denser training crowds: this many time-shifted copies of each replayed recording are overlaid on it
    (:func:`envs.recordings.overlay_recording`; shifts evenly spaced within the ``episode_time`` window, so the
    training and validation periods never mix). Only with ``part="train"``: the held-out scene is never used."""

    # ----------------------------------------------------------------- observation
    num_pedestrians: int = 10
    """K: the K nearest pedestrians within the sensor range are observed."""
    sensor_range_m: float = 6.0
    """Pedestrians farther than this (centre distance) are not observed, metres."""
    horizon_steps: int = 12
    """H: forecast steps of dt_s each (12 x 0.4 s = 4.8 s)."""
    max_obs_speed_mps: float = 4.0
    """Pedestrian speeds in the observation are clipped to this, m/s (bounds of the observation space)."""
    max_goal_offset_m: float = 50.0
    """Goal offset components are clipped to ±this, metres."""
    observe_time_left: bool = False
    """Append the fraction of the time limit left, in [0, 1], to ``robot`` (1 at reset, 0 at the last step)."""
    observe_perception_age: bool = False
    """Append the age of the perceived annotation, seconds (clipped to [0, 1]), to ``robot`` (after the time left).
    Pedestrians are perceived at the latest annotation at or before the current time: always 0 on 0.4 s
    recordings stepped at 0.4 s, 0 to 0.53 s on ``biwi_eth`` (0.667 s annotations)."""
    flatten_observation: bool = True
    """Give ``pedestrians`` and ``forecasts`` as 1-D vectors (row-major ``(K, 4)`` and ``(K, H, 2)``), as
    Stable-Baselines3 expects; False gives them those shapes (see :func:`envs.observation.structured`)."""
    forecast_uncertainty: bool = False
    """Add ``forecast_uncertainty`` ``(K, H)`` to the observation (arms with forecasts): per forecast step, the
    radius (m) of a disc around the forecast holding the true position with probability
    ``forecast_uncertainty_level``, calibrated on the split's validation windows
    (:mod:`envs.forecasting.uncertainty`)."""
    forecast_uncertainty_level: float = 0.9
    """Coverage level of the ``forecast_uncertainty`` radii, in (0, 1)."""
    forecast_uncertainty_method: str = "split"
    """How each forecast step's threshold is set: ``split`` (split conformal, fixed on the split's validation windows)
    or ``online`` (the strictly causal ``observed`` rule with step-size experts of
    :mod:`crowdnav_mesrnn.uncertainty.online_conformal`, run inside each episode: it starts from the split thresholds
    at the episode's first annotation and learns from how far the episode's earlier forecasts missed, as their truth
    is annotated; it restarts every episode). ``online`` needs a named forecast source's window forecasts and
    ``reaction: none``."""
    forecast_samples: int = 0
    """Add ``forecast_samples`` ``(K, S, H, 2)`` to the observation: ``S`` (this many) sampled futures of each observed
    pedestrian at ``t + h * dt_s``, relative to the robot, drawn from the forecast source's distribution (the Gaussian
    head of ``mesrnn``, ``srnn``, ``vlstm``: their shipped ``gaussian`` weights of the split, beside the point weights
    of ``forecasts``; ``cv_gaussian``'s own), coherently, with a seed fixed by the recording and the time
    (:mod:`envs.forecasting.samples`). 0: none. Only for those sources, ``forecast_memory: window`` and ``reaction:
    none``."""

    # ----------------------------------------------------------------- forecasts
    cache_forecasts: bool = True
    """Keep forecasts per recording (chunks of annotation frames, computed in batched passes) instead of computing
    each when needed; identical to the online path (replayed pedestrians ignore the robot)."""
    forecast_disk_cache: bool = True
    """Share learned forecasts between processes through files in ``forecast_cache_dir`` (with
    ``cache_forecasts``): computed once per (weights, recording, settings), loaded by every later process."""
    forecast_cache_dir: str | None = None
    """Folder of the shared forecast cache; default: ``$CROWDNAV_MESRNN_CACHE``, else
    ``~/.cache/crowdnav-mesrnn/forecasts``."""
    forecast_memory: str = "window"
    """How a learned predictor remembers the past. ``window`` (the evaluated protocol, as in training and
    ADE/FDE): at every time a fresh rollout from the last 8 annotation steps (3.2 s; 5.3 s on ``biwi_eth``).
    ``carried``: hidden states carried per pedestrian from its first appearance in the recording (one
    ``online()`` forecaster slot per pedestrian id, fed every annotation frame in order); forecasts are taken at
    the latest annotation at or before the current time. Only ``mesrnn``, ``srnn``, ``vlstm`` and predictor
    objects with an ``online(num_slots)`` method support ``carried`` (another object raises ConfigError);
    ``none``, ``cv``, ``oracle`` and ``noisy_oracle`` have no memory and ignore it."""
    noisy_oracle_ade_m: float = 0.5
    """``noisy_oracle``: expected ADE of the noise added to the true future, metres."""

    # ----------------------------------------------------------------- reward (identical in every forecast arm)
    success_reward: float = 10.0
    """Reward when the goal is reached."""
    collision_penalty: float = -20.0
    """Reward on a step with a robot-pedestrian contact."""
    discomfort_dist_m: float = 0.25
    """Gaps below this are uncomfortable, metres."""
    discomfort_scale: float = 10.0
    """Discomfort = (gap - discomfort_dist_m) x scale x dt_s when gap < discomfort_dist_m, per metre-second."""
    progress_weight: float = 1.0
    """Weight of the potential-based progress term gamma * phi(s') - phi(s), phi = -distance to goal."""
    progress_gamma: float = 0.99
    """gamma of the progress term (use the agent's discount factor)."""
    intrusion_penalty: float = 0.0
    """Reward per step when the robot stands on a pedestrian's true future path within the horizon (0 = off)."""
    time_penalty: float = 0.0
    """Reward added at every step (component ``time``; e.g. -0.01 to favour short episodes; 0 = off)."""

    # ----------------------------------------------------------------- synthetic crowd
    synthetic_duration_s: float = 300.0
    """Length of the generated social-force recording, seconds."""
    synthetic_arrival_rate_per_s: float = 0.8
    """Pedestrians entering the synthetic scene per second."""
    synthetic_area_m: tuple[float, float] = (16.0, 12.0)
    """Width and height of the synthetic scene, metres."""
    synthetic_seed: int = 0
    """Seed of the synthetic recording (fixed: the scene is data, episodes are seeded by reset)."""

    # ----------------------------------------------------------------- rendering
    render_px_per_m: float = 40.0
    """Fixed scale of the rendering, pixels per metre."""
    render_size_px: tuple[int, int] = (640, 640)
    """Width and height of rendered frames, pixels: a title strip above the scene and a legend strip below it
    (``envs.rendering.frame_layout``; small frames have neither), the scene in the rest."""
    render_trail_steps: int = 8
    """Length of the pedestrians' trails, control steps."""

    def __post_init__(self) -> None:
        # the reaction constants, resolved onto their defaults (a ConfigError names a bad key or value)
        object.__setattr__(self, "reaction_params", ReactionParams.from_mapping(self.reaction_params).to_dict())

    @property
    def reaction_parameters(self) -> ReactionParams:
        """:attr:`reaction_params` as a :class:`~envs.reaction.ReactionParams`."""
        return ReactionParams(**self.reaction_params)

    @property
    def substeps(self) -> int:
        """Physics substeps per control step."""
        return max(1, math.ceil(self.dt_s / self.physics_dt_s - 1e-9))

    @property
    def horizon_s(self) -> float:
        return self.horizon_steps * self.dt_s

    def validate(self) -> CrowdNavConfig:
        """Check the type, finiteness and range of every value (:func:`check_value`) and how values go together;
        raise :class:`ConfigError` naming the key, the value and what is allowed (valid values are listed for
        choices). Returns self."""
        for spec in dataclasses.fields(self):
            check_value(spec.name, getattr(self, spec.name))
        resolve_scenes(self.scenes, episode_recordings(self.split, self.part), self.split, self.part)
        if self.start_goal_distance_m[0] <= self.goal_tolerance_m:
            raise ConfigError(
                f"config key 'start_goal_distance_m' = {self.start_goal_distance_m!r} must start above "
                f"'goal_tolerance_m' = {self.goal_tolerance_m!r} (else the robot starts at its goal)"
            )
        if self.crowd_overlays and self.part != "train":
            raise ConfigError(
                f"config key 'crowd_overlays' = {self.crowd_overlays!r} densifies training crowds only: it needs "
                f"part 'train', got {self.part!r} (the held-out scene is replayed as recorded)"
            )
        substeps = self.dt_s / self.physics_dt_s
        if substeps > MAX_SUBSTEPS + 1e-9:
            raise ConfigError(
                f"config keys 'dt_s' = {self.dt_s!r} and 'physics_dt_s' = {self.physics_dt_s!r} give {substeps:.3g} "
                f"substeps per control step; at most {MAX_SUBSTEPS} are allowed"
            )
        substep_s = self.dt_s / self.substeps
        closing_m = (1.5 + self.robot_pref_speed_mps) * substep_s
        if closing_m > self.robot_radius_m + self.pedestrian_radius_m:
            raise ConfigError(
                f"config key 'physics_dt_s' = {self.physics_dt_s!r} is too long for 'robot_pref_speed_mps' = "
                f"{self.robot_pref_speed_mps!r}: a 1.5 m/s pedestrian and the robot close {closing_m:.3g} m per substep, "
                f"more than the sum of radii {self.robot_radius_m + self.pedestrian_radius_m:.3g} m (contacts could be "
                "missed)"
            )
        return self


def check_value(key: str, value: Any) -> None:
    """Raise :class:`ConfigError` unless ``value`` is allowed for ``key`` on its own (type, finiteness, range;
    how keys go together is checked by :meth:`CrowdNavConfig.validate`)."""
    if key == "predictor":
        predictors.check(value)
    elif key == "reaction":
        check_model(value)
    elif key == "reaction_params":
        ReactionParams.from_mapping(value)
    elif key in _CHOICES:
        _one_of(key, value, _CHOICES[key])
    elif key == "scenes":
        if not (isinstance(value, tuple) and all(isinstance(x, str) for x in value)):
            raise ConfigError(f"config key 'scenes' must be a list of recording or scene names, got {value!r}")
    elif key in ("data_dir", "forecast_cache_dir"):
        if value is not None and not (isinstance(value, str | os.PathLike) and str(value)):
            raise ConfigError(f"config key {key!r} must be a folder path or null, got {value!r}")
    elif key in _FLAGS:
        if not isinstance(value, bool | np.bool_):
            raise ConfigError(f"config key {key!r} must be true or false, got {value!r}")
    elif key in _NUMBERS:
        _number(key, value, *_NUMBERS[key])
    elif key in _INTEGERS:
        lo, hi = _INTEGERS[key]
        ok = isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)
        if not (ok and value >= lo and (hi is None or value <= hi)):
            what = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
            raise ConfigError(f"config key {key!r} must be an integer {what}, got {value!r}")
    elif key == "start_goal_distance_m":
        dist = _pair(key, value, "(min, max) metres")
        if not 0 < dist[0] <= dist[1]:
            raise ConfigError(f"config key {key!r} must be (min, max) with 0 < min <= max, got {value!r}")
    elif key == "synthetic_area_m":
        if min(_pair(key, value, "(width, height) metres")) < 4:
            raise ConfigError(f"config key {key!r} must be (width, height) of at least 4 m, got {value!r}")
    elif key == "render_size_px":
        size = _pair(key, value, "(width, height) pixels")
        if not (all(16 <= v <= MAX_RENDER_PX for v in size) and all(v.is_integer() for v in size)):
            raise ConfigError(
                f"config key {key!r} must be (width, height) integers in [16, {MAX_RENDER_PX}] px, got {value!r}"
            )
    else:  # pragma: no cover (a new field without a check)
        raise ConfigError(f"config key {key!r} has no check")


#: Longest physics substep count per control step (``dt_s / physics_dt_s``).
MAX_SUBSTEPS: Final[int] = 1000
#: Largest rendered frame side, pixels.
MAX_RENDER_PX: Final[int] = 4096
#: Keys with a fixed set of string values.
_CHOICES: Final[dict[str, tuple[str, ...]]] = {
    "split": SPLITS,
    "part": EPISODE_PARTS,
    "crowd": CROWDS,
    "kinematics": KINEMATICS,
    "forecast_memory": FORECAST_MEMORIES,
    "episode_time": EPISODE_TIMES,
    "forecast_uncertainty_method": UNCERTAINTY_METHODS,
}
#: Boolean keys.
_FLAGS: Final[tuple[str, ...]] = (
    "terminate_on_collision",
    "require_pedestrians",
    "observe_time_left",
    "observe_perception_age",
    "flatten_observation",
    "forecast_uncertainty",
    "cache_forecasts",
    "forecast_disk_cache",
)
#: Integer keys -> (smallest, largest or None) allowed value.
_INTEGERS: Final[dict[str, tuple[int, int | None]]] = {
    "num_pedestrians": (1, 1000),
    "horizon_steps": (1, 1000),
    "render_trail_steps": (1, 10_000),
    "synthetic_seed": (0, None),
    "crowd_overlays": (0, 100),
    "forecast_samples": (0, 1000),
}
#: Real keys -> (low, high, low open, high open); None = unbounded. Every one must also be finite.
_NUMBERS: Final[dict[str, tuple[float | None, float | None, bool, bool]]] = {
    "robot_radius_m": (0.0, None, True, False),
    "robot_pref_speed_mps": (0.0, None, True, False),
    "robot_max_turn_rate_radps": (0.0, None, True, False),
    "pedestrian_radius_m": (0.0, None, True, False),
    "dt_s": (0.0, None, True, False),
    "physics_dt_s": (0.0, None, True, False),
    "start_clearance_m": (0.0, None, False, False),
    "time_limit_factor": (0.0, None, True, False),
    "goal_tolerance_m": (0.0, None, True, False),
    "val_fraction": (0.0, 1.0, True, True),
    "sensor_range_m": (0.0, None, True, False),
    "max_obs_speed_mps": (0.0, None, True, False),
    "max_goal_offset_m": (0.0, None, True, False),
    "noisy_oracle_ade_m": (0.0, None, False, False),
    "forecast_uncertainty_level": (0.0, 1.0, True, True),
    "success_reward": (None, None, False, False),
    "collision_penalty": (None, None, False, False),
    "discomfort_dist_m": (0.0, None, False, False),
    "discomfort_scale": (0.0, None, False, False),
    "progress_weight": (None, None, False, False),
    "progress_gamma": (0.0, 1.0, True, False),
    "intrusion_penalty": (None, None, False, False),
    "time_penalty": (None, None, False, False),
    "synthetic_duration_s": (1.0, None, False, False),
    "synthetic_arrival_rate_per_s": (0.0, None, False, False),
    "render_px_per_m": (0.0, None, True, False),
}


def _is_real(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)


def _number(key: str, value: Any, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> None:
    """Raise unless ``value`` is a finite real number in the interval."""
    if lo is None and hi is None:
        what = "a finite number"
    elif hi is None:
        what = f"a number {'>' if lo_open else '>='} {lo:g}"
    else:
        what = f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    ok = _is_real(value) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if not ok:
        raise ConfigError(f"config key {key!r} must be {what}, got {value!r}")


def _one_of(key: str, value: Any, valid: tuple[str, ...]) -> None:
    if not isinstance(value, str) or value not in valid:
        raise ConfigError(f"unknown {key} {value!r}; valid: {', '.join(valid)}")


def _pair(key: str, value: Any, what: str) -> tuple[float, float]:
    """Two finite real numbers, or :class:`ConfigError`."""
    if not (isinstance(value, tuple) and len(value) == 2 and all(_is_real(v) and math.isfinite(v) for v in value)):
        raise ConfigError(f"config key {key!r} must be {what}: two finite numbers, got {value!r}")
    return float(value[0]), float(value[1])


def episode_recordings(split: str, part: str) -> tuple[str, ...]:
    """Recordings (whole files in ``all_data/``) an episode of ``split``/``part`` may replay.

    ``test``: the split's held-out recording(s). ``train``: the held-out recordings of the four other
    splits. ``crowds_zara03`` and ``uni_examples`` (training data of every predictor) are never replayed.
    """
    _one_of("split", split, SPLITS)
    _one_of("part", part, EPISODE_PARTS)
    if part == "test":
        return SPLIT_TEST_RECORDINGS[split]
    return tuple(r for s, recs in SPLIT_TEST_RECORDINGS.items() if s != split for r in recs)


def resolve_scenes(scenes: tuple[str, ...], allowed: tuple[str, ...], split: str, part: str) -> tuple[str, ...]:
    """Recording names selected by ``scenes`` (recording names or scene labels); all of ``allowed`` if empty."""
    if not scenes:
        return allowed
    valid_labels = sorted({RECORDINGS[r] for r in allowed})
    out: list[str] = []
    for scene in scenes:
        if scene in allowed:
            names = [scene]
        else:
            names = [r for r in allowed if RECORDINGS[r] == scene]
        if not names:
            raise ConfigError(
                f"unknown scene {scene!r} for split {split!r}, part {part!r}; valid: "
                f"{', '.join([*allowed, *valid_labels])}"
            )
        out.extend(n for n in names if n not in out)
    return tuple(out)


def config_mapping(config: Mapping[str, Any] | str | os.PathLike[str] | None) -> dict[str, Any]:
    """The keys ``config`` (a mapping, a YAML file or None) sets, as a dict (nothing merged, nothing checked)."""
    if config is None:
        return {}
    if isinstance(config, Mapping):
        return dict(config)
    if isinstance(config, str | os.PathLike):
        return load_yaml(config)
    raise ConfigError(f"config must be a mapping or a YAML path, got {type(config).__name__}")


def config_from(
    config: Mapping[str, Any] | str | os.PathLike[str] | None, overrides: Mapping[str, Any]
) -> CrowdNavConfig:
    """Defaults, then ``config`` (a mapping or a YAML file), then keyword ``overrides``; validated."""
    base = config_mapping(config)
    # an unknown keyword is a TypeError too, worded as Python's (crowdnav_mesrnn.config.UnknownKeyError)
    check_keys(overrides, [f.name for f in dataclasses.fields(CrowdNavConfig)], "env config", keywords=True)
    # a value of ``config`` a keyword overrides (the id's predictor, say) is still checked: nonsense is refused,
    # never silently dropped
    for key in set(base) & set(overrides):
        shadowed = replace_checked(CrowdNavConfig(), {key: base[key]}, where="env config")
        check_value(key, getattr(shadowed, key))
    merged = {**base, **overrides}
    cfg = replace_checked(CrowdNavConfig(), merged, where="env config")
    return cfg.validate()


@dataclass(frozen=True)
class CrowdSource:
    """Where an environment's crowd comes from (named in every result: evaluation summaries, run folders)."""

    kind: str
    """``replay`` (ETH/UCY recordings), ``synthetic`` (the project's social-force crowd), ``empty`` or ``custom`` (a
    :class:`~crowdnav_mesrnn.data.Recording` object passed as ``crowd=``)."""
    data_dir: str | None = None
    """The ETH/UCY folder replayed (``replay`` only)."""
    embedded_default: bool = False
    """The synthetic crowd replaces the ETH/UCY data of a bare ``gymnasium.make(id)`` (``crowd="auto"``, no scene named,
    no data found)."""

    def describe(self) -> str:
        """One line for messages and tables: ``ETH/UCY replay from /data/eth_ucy``, ``synthetic crowd``, ..."""
        if self.kind == "replay":
            return f"ETH/UCY replay from {self.data_dir}"
        if self.kind == "synthetic" and self.embedded_default:
            return "synthetic crowd (the embedded default: no scene named, no ETH/UCY data found)"
        return {"synthetic": "synthetic crowd", "empty": "empty scene"}.get(self.kind, f"{self.kind} crowd")

    def as_dict(self) -> dict[str, Any]:
        """``{"kind", "data_dir"}`` for JSON and YAML files."""
        return {"kind": self.kind, "data_dir": self.data_dir}


def crowd_source(cfg: CrowdNavConfig, scene_named: bool) -> CrowdSource:
    """The crowd a configuration replays, looking for the ETH/UCY data where ``crowd`` asks for it.

    Args:
        cfg: the configuration (``crowd``, ``data_dir``, ``split``, ``part``, ``scenes``).
        scene_named: the user named ETH/UCY scenes (gave any of :data:`SCENE_KEYS`); :func:`names_scene` tells.

    Raises:
        DataNotFoundError: ``crowd`` is ``replay``, or ``auto`` with a scene named or ``data_dir`` given, and no data
            is found; the message names every place looked at and how to ask for the synthetic crowd instead.
    """
    if cfg.crowd in ("empty", "synthetic"):
        return CrowdSource(cfg.crowd)
    try:
        return CrowdSource("replay", str(find_data_dir(cfg.data_dir)))
    except DataNotFoundError as exc:
        if cfg.crowd == "replay" or scene_named or cfg.data_dir is not None:
            names = resolve_scenes(cfg.scenes, episode_recordings(cfg.split, cfg.part), cfg.split, cfg.part)
            raise DataNotFoundError(
                f"split {cfg.split!r}, part {cfg.part!r} replays the ETH/UCY recording(s) {', '.join(names)}, but {exc}\n"
                "Pass crowd='synthetic' to run on the project's synthetic crowd instead (agents.evaluate: --set "
                "crowd=synthetic; agents.train: --set env.crowd=synthetic)."
            ) from None
        return CrowdSource("synthetic", embedded_default=True)


def names_scene(config: Mapping[str, Any] | str | os.PathLike[str] | None, overrides: Mapping[str, Any]) -> bool:
    """True when ``config`` or ``overrides`` sets any of :data:`SCENE_KEYS` (then ``crowd="auto"`` needs the data)."""
    return bool(set(SCENE_KEYS) & (set(config_mapping(config)) | set(overrides)))


def default_config() -> dict[str, Any]:
    """The defaults as a flat dict (tuples as lists, YAML-ready)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(CrowdNavConfig()).items()}


#: Names this module used to define, now asked of the predictor registry: name -> (replacement, value).
_MOVED: Final[dict[str, tuple[str, Callable[[], Any]]]] = {
    "FORECAST_SOURCES": ("names(plugins=False)", lambda: predictors.names(plugins=False)),
    "LEARNED_SOURCES": (
        "names(PRETRAINED, plugins=False)",
        lambda: predictors.names(predictors.PRETRAINED, plugins=False),
    ),
    "is_plugin_source": ("is_plugin", lambda: predictors.is_plugin),
    "forecast_source_names": ("names", lambda: predictors.names),
    "check_predictor_name": ("check", lambda: predictors.check),
}


def __getattr__(name: str) -> Any:
    """The predictor names this module used to define, with a DeprecationWarning: the registry
    (:mod:`crowdnav_mesrnn.predictors`) is the one place that knows them."""
    moved = _MOVED.get(name)
    if moved is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(
        f"envs.config.{name} is deprecated; use crowdnav_mesrnn.predictors.{moved[0]}",
        DeprecationWarning,
        stacklevel=2,
    )
    return moved[1]()
