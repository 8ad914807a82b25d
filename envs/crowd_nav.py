"""The crowd-navigation environment ``CrowdNav-MESRNN-v0`` and its forecast variants (one class)."""

from __future__ import annotations

import importlib.util
import math
import os
import warnings
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import DependencyNotInstalled

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, check_keys
from crowdnav_mesrnn.data.constants import OBS_LEN
from crowdnav_mesrnn.data.paths import HOW_TO_GET_DATA
from crowdnav_mesrnn.data.recordings import Recording, load_recording
from envs.config import (
    CrowdNavConfig,
    CrowdSource,
    config_from,
    crowd_source,
    episode_recordings,
    names_scene,
    resolve_scenes,
)
from envs.episodes import Episode, EpisodeSampler, episode_time_window
from envs.forecasting.factory import make_forecast_source
from envs.forecasting.observed import needs_observed, observed_forecasts
from envs.forecasting.samples import SampleSource, make_sample_source
from envs.forecasting.sources import ForecastModel, ForecastSource, TrueFuture, fill_forward
from envs.forecasting.uncertainty import UncertaintySource, make_uncertainty_source
from envs.forecasting.window import PredictorForecast
from envs.observation import ObservationBuilder, nearest_visible, observation_space
from envs.popin import POPIN_MARGIN_M, PopInRule
from envs.reaction import revision_rules
from envs.reactive import ReactionSnapshot, ReactiveWorld
from envs.recordings import empty_recording, overlay_recording, synthetic_recording
from envs.rendering import HUMAN_NEEDS_PYGAME
from envs.replay import Replay
from envs.rewards import EpisodeMetrics, min_time_to_collision, reward_components, total_reward
from envs.timing import PhaseTimer, timed
from envs.world import World, robot_path

#: Default of ``CrowdNavEnv(predictor=...)``: the config's ``predictor`` (an explicit None is an error).
_CONFIGURED: Final[Any] = object()
#: Keys accepted in ``reset(options=...)``.
RESET_OPTIONS: Final[tuple[str, ...]] = ("recording", "t0_s", "start", "goal", "time_limit_s")
TIMING_KEYS: Final[tuple[str, ...]] = ("replay", "physics", "reaction", "forecasts", "observation", "reward", "reset")
#: Revision of the environment's rules (episodes, physics, perception), in every reset ``info`` and evaluation
#: summary, so a result says which rules it ran under; bumped whenever the same seed can give another episode
#: (see the class docstring's Version History). With ``reaction="none"`` (the default) episodes are those of
#: revision 1 bit for bit; the reaction model and its parameters are the rest of the identity (:func:`env_rules`).
ENV_REVISION: Final[int] = 1
#: The disturbance metrics (``info["episode_metrics"]``) of an episode in which nobody reacts.
UNDISTURBED: Final[dict[str, Any]] = {
    "ped_disturbed": 0,
    "ped_deviation_mean_m": 0.0,
    "ped_deviation_max_m": 0.0,
    "ped_delay_s": 0.0,
}


def env_rules(config: CrowdNavConfig | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The identity of the rules an environment runs under, for every result's spec: ``{"env_revision":
    ENV_REVISION}`` under ``reaction="none"`` (so results of revision 1 stay valid as they are), plus ``reaction``
    and ``reaction_params`` (every constant, :meth:`envs.reaction.ReactionParams.to_dict`) under a reaction model,
    and ``reaction_revision`` for a model past its first revision (:data:`envs.reaction.MODEL_REVISIONS`).

    Args:
        config: the environment's configuration (a :class:`~envs.config.CrowdNavConfig`, or a mapping of settings
            merged onto the defaults); None: the defaults.
    """
    cfg = config if isinstance(config, CrowdNavConfig) else config_from(config or {}, {})
    rules: dict[str, Any] = {"env_revision": ENV_REVISION}
    if cfg.reaction != "none":
        rules.update(reaction=cfg.reaction, reaction_params=dict(cfg.reaction_params), **revision_rules(cfg.reaction))
    return rules


@dataclass(frozen=True)
class _Moved:
    """What the physics phase of a step produced."""

    robot_before: np.ndarray
    robot_after: np.ndarray
    positions: np.ndarray  # (1 + H, N, 2) replay positions at t_next + h * dt_s
    present: np.ndarray  # (1 + H, N); row 0 without the pop-in ghosts
    gap_m: float  # smallest surface gap during the step (substeps after its start)
    collided: bool
    fault: str | None
    new_contacts: int


@dataclass(frozen=True)
class _Sensed:
    """What the perception phase found in the world (for the reward): gap and intrusion at the step's end, and how
    many pedestrians the robot perceives."""

    gap_m: float
    intruding: bool
    visible: int
    ttc_s: float = math.inf  # smallest constant-velocity time to collision at the step's end (envs.rewards)


def _grid_time(k0: int | None, t0_s: float, dt_s: float, n: int) -> float:
    """Time of step ``n`` of an episode starting at ``t0_s``: ``(k0 + n) * dt_s`` when ``t0_s`` is on the ``dt_s`` grid
    at index ``k0``, else ``t0_s + n * dt_s``."""
    return (k0 + n) * dt_s if k0 is not None else t0_s + n * dt_s


def reset_options(options: Any, goal_tolerance_m: float) -> dict[str, Any]:
    """``reset(options=...)`` checked: a mapping with keys among :data:`RESET_OPTIONS`, each of the right type,
    finite and in range; ``ValueError`` (``ConfigError`` for unknown keys) naming the option, the value and what
    is allowed. Whether ``recording`` exists and ``t0_s`` lies inside it is checked when the episode is drawn."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ValueError(f"reset options must be a mapping with keys among {', '.join(RESET_OPTIONS)}, got {options!r}")
    opts = dict(options)
    check_keys(opts, RESET_OPTIONS, "reset option")
    if "recording" in opts and not isinstance(opts["recording"], str):
        raise ValueError(f"reset option 'recording' must be a recording name, got {opts['recording']!r}")
    for key, positive in (("t0_s", False), ("time_limit_s", True)):
        if key in opts:
            value = opts[key]
            real = isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)
            if not (real and math.isfinite(value) and (value > 0 if positive else value >= 0)):
                raise ValueError(
                    f"reset option {key!r} must be a finite number of seconds {'> 0' if positive else '>= 0'}, "
                    f"got {value!r}"
                )
            opts[key] = float(value)
    for key in ("start", "goal"):
        if key in opts:
            try:
                arr = np.asarray(opts[key])
                arr = np.zeros(0) if arr.dtype.kind not in "iuf" else arr.astype(np.float64)  # no bools, strings
            except (TypeError, ValueError):
                arr = np.zeros(0)
            if arr.shape != (2,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"reset option {key!r} must be 2 finite numbers (metres), got {opts[key]!r}")
            opts[key] = arr
    if "start" in opts and "goal" in opts:
        dist = float(np.linalg.norm(opts["goal"] - opts["start"]))
        if dist <= goal_tolerance_m:
            raise ValueError(
                f"reset options 'start' {opts['start'].tolist()} and 'goal' {opts['goal'].tolist()} are {dist:.3g} m "
                f"apart: they must be more than goal_tolerance_m = {goal_tolerance_m} m apart"
            )
    return opts


def reset_info(
    ep: Episode, crowd: str, predictor: str, reaction: str, reaction_params: Mapping[str, Any]
) -> dict[str, Any]:
    """The reset ``info`` of an episode (see :class:`CrowdNavEnv`'s Starting State); ``reaction_params`` is copied."""
    return {
        "recording": ep.recording.name,
        "crowd": crowd,
        "predictor": predictor,
        "t0_s": ep.t0_s,
        "start": ep.start.tolist(),
        "goal": ep.goal.tolist(),
        "time_limit_s": ep.time_limit_s,
        "crowd_density": ep.crowd_density,
        "pedestrians_near_path": ep.pedestrians_near_path,
        "env_revision": ENV_REVISION,
        "reaction": reaction,
        "reaction_params": dict(reaction_params),
        **revision_rules(reaction),
    }


class CrowdNavEnv(gym.Env[dict[str, np.ndarray], np.ndarray]):
    """A robot disk crosses an ETH/UCY crowd replayed in a pymunk world, with forecasts of every
    observed pedestrian in its observation.

    ## Description

    Each episode replays a time window of one of the five ETH/UCY scenes' test recordings
    (``biwi_eth``, ``biwi_hotel``, ``students001``/``students003``, ``crowds_zara01``,
    ``crowds_zara02``) in continuous time: pedestrian positions are interpolated linearly between
    annotations, which are 0.4 s apart (0.667 s for ``biwi_eth``), and equal the file at every
    annotation time. Pedestrians appear and leave as in the data and, by default (``reaction="none"``), ignore the
    robot. ``reaction="pause"``, ``"orca"`` or ``"social_force"`` lets them react (:mod:`envs.reactive`,
    ``docs/reaction.md``): each follows its recording bit for bit until the robot comes near, is then moved by a
    model of reaction (not measured people) and rejoins its recording; the reset ``info`` names the ``reaction`` and
    its ``reaction_params``. The robot, a disk of radius 0.3 m, must reach a goal 6-12 m away whose straight path
    crosses where people walk. ``split``/``part`` choose the recordings: ``part="test"`` replays the split's held-out
    scene, ``part="train"`` the four others. Naming a scene (``split``, ``part`` or ``scenes``) without the
    ETH/UCY data on disk is a ``DataNotFoundError`` naming where the project looked. ``crowd="synthetic"``
    replays a social-force crowd generated by the project; so does a bare ``gymnasium.make(id)`` (no scene
    named) without the data, as the embedded default, with a warning. ``crowd_source`` names the crowd
    (``kind``, the data folder); the reset ``info["crowd"]`` its kind.

    The variants differ only in the forecast source (``predictor``): ``CrowdNav-MESRNN-v0``
    (``mesrnn``), ``CrowdNav-NoPred-v0`` (``none``), ``CrowdNav-CV-v0`` (``cv``) and
    ``CrowdNav-Oracle-v0`` (``oracle``); ``srnn``, ``vlstm`` and ``noisy_oracle`` are available as
    keywords. Learned forecasts are out-of-sample: a recording is always forecast by the
    pretrained predictor of the split that held its scene out, for training and testing alike.
    Reward, termination and metrics are identical in every arm.

    ## Action Space

    ``Box(-1, 1, (2,), float32)``, clipped to [-1, 1]; NaN, infinite or wrongly shaped actions raise
    ``ValueError``.

    | kinematics | index | meaning | scaled by |
    |---|---|---|---|
    | ``holonomic`` (default) | 0, 1 | velocity x, y (norm clipped to 1) | ``robot_pref_speed_mps`` |
    | ``unicycle`` | 0 | forward speed (negative = reverse) | ``robot_pref_speed_mps`` |
    | ``unicycle`` | 1 | turn rate | ``robot_max_turn_rate_radps`` |

    ## Observation Space

    ``Dict`` of float32 arrays (and an int8 mask), fresh at every step. Positions are relative to the
    robot, axes of the world frame. K = ``num_pedestrians`` (10), H = ``horizon_steps`` (12),
    v = ``robot_pref_speed_mps``, s = ``max_obs_speed_mps`` (4), R = ``sensor_range_m`` (6).

    | key | shape | meaning | min | max | unit |
    |---|---|---|---|---|---|
    | ``robot`` [0:2] | (2,) | goal minus robot position | -50 | 50 | m |
    | ``robot`` [2:4] | (2,) | robot velocity | -v | v | m/s |
    | ``robot`` [4:6] | (2,) | cos, sin of the heading (unicycle only) | -1 | 1 | |
    | ``robot`` [+1] | (1,) | fraction of the time limit left (``observe_time_left`` only) | 0 | 1 | |
    | ``robot`` [+1] | (1,) | age of the perceived annotation, s (``observe_perception_age`` only) | 0 | 1 | s |
    | ``pedestrians`` [:, 0:2] | (K, 2) | pedestrian minus robot position, nearest first (*) | -R | R | m |
    | ``pedestrians`` [:, 2:4] | (K, 2) | pedestrian minus robot velocity (*) | -(s+v) | s+v | m/s |
    | ``mask`` | (K,) | 1 where the row holds a pedestrian within R | 0 | 1 | |
    | ``forecasts`` | (K, H, 2) | forecast position at t + h dt minus robot position (absent for ``none``) | -(R+sHdt) | R+sHdt | m |
    | ``forecast_uncertainty`` | (K, H) | radius of the calibrated region around each forecast (``forecast_uncertainty`` only) | 0 | R+sHdt | m |
    | ``forecast_samples`` | (K, S, H, 2) | S sampled futures at t + h dt minus robot position (``forecast_samples`` = S > 0 only) | -(R+sHdt) | R+sHdt | m |

    (*) Pedestrians are perceived causally, as a tracker reporting at the recording's annotation rate:
    at time t the latest annotation at or before t (its positions; velocities = the slope of the
    interval ending there, 0 for a pedestrian that has just appeared; presence = annotated there and
    less than one annotation step old), and forecasts come from that same annotation, resampled onto
    t + h dt. Nothing annotated after t enters the observation (on ``biwi_eth``, whose 0.667 s
    annotations fall between control steps, positions are up to 0.53 s old). The world (physics,
    contacts, gaps, intrusion, the oracle's truth) interpolates between annotations. With a reaction model the
    robot perceives where the pedestrians actually were at the annotation times, and forecasts come from those
    observed histories (the per-recording cache where they are the recorded ones). ``oracle`` and
    ``noisy_oracle`` always give the recorded future, what each person would have done without the robot: a
    counterfactual, not the truth, once people react (``pause``: the person's own time-shifted recording).

    **Pedestrians do not appear on the robot** (:mod:`envs.popin`). A track that begins (or resumes after a
    gap) with its centre closer than the sum of radii plus ``POPIN_MARGIN_M`` (0.1 m) to the robot's is a
    *ghost*: no contacts, no gap, not perceived, until the first physics substep end or annotation time at which
    its recorded position is that far from the robot; from then on it is an ordinary pedestrian. Perception
    drops a pedestrian that was a ghost at the annotation it reports (so it stays causal between ``biwi_eth``
    annotations). The rule is the same in every arm; ``info["episode_metrics"]["popin_events"]`` counts the
    ghosted appearances of an episode.

    ## Rewards

    The reward is the sum of the components in ``info["reward_components"]``:
    ``success`` (+10 on reaching the goal), ``collision`` (-20 on a step with a contact),
    ``discomfort`` (``(gap - 0.25) * 10 * dt`` when the smallest gap to a pedestrian during the step
    is under 0.25 m), ``progress`` (``gamma * phi(s') - phi(s)``, ``phi = -distance to goal``,
    gamma = ``progress_gamma``), ``intrusion`` (``intrusion_penalty``, default 0, when the robot
    stands on a pedestrian's true future path within the horizon — the recorded one, never from the
    arm's forecasts) and ``time`` (``time_penalty`` at every step, default 0). All values are
    configurable.

    ## Starting State

    A recording (weighted by duration), a start time on the ``dt_s`` grid leaving room for 8
    annotations of history and the whole episode, and a start/goal pair
    ``start_goal_distance_m`` apart inside the scene, on a straight line through a position a
    pedestrian occupies during the episode, with no pedestrian within ``start_clearance_m`` (gap)
    of the start. The robot starts at rest facing the goal. With ``episode_time="train"``/``"val"``
    episodes lie wholly before/inside the last ``val_fraction`` of each recording's duration; with
    ``require_pedestrians`` episodes are redrawn until a pedestrian comes within ``sensor_range_m``
    of the straight start-goal segment. All randomness comes from ``reset(seed=...)``;
    ``reset(options=...)`` may fix ``recording``, ``t0_s``, ``start``, ``goal`` and ``time_limit_s``.
    The reset ``info`` holds ``recording``, ``crowd``, ``predictor``, ``t0_s``, ``start``, ``goal``,
    ``time_limit_s``, ``env_revision`` (:data:`ENV_REVISION`, the revision of the rules), ``reaction`` and
    ``reaction_params`` (the rest of the rules' identity, :func:`env_rules`), ``crowd_density``
    (mean number of pedestrians within ``sensor_range_m`` of the start-goal segment at the annotation times of
    the episode, frames the file skips counting as empty) and ``pedestrians_near_path``.

    ## Episode End

    Terminated when the robot's centre is within ``goal_tolerance_m`` of the goal (success), or at a
    robot-pedestrian contact reported by pymunk (collision; ``info["collision_fault"]`` says whether
    the robot or the pedestrian moved faster towards the other). With
    ``terminate_on_collision=False`` the episode continues and every step in contact is penalised.
    Truncated at the time limit, ``time_limit_factor`` (3) x straight-line distance / preferred
    speed. The last step's ``info["episode_metrics"]`` holds the episode metrics (see
    :meth:`envs.rewards.EpisodeMetrics.summary`) and what the robot did to people
    (:class:`envs.reaction.DisturbanceMetrics`: ``ped_disturbed``, ``ped_deviation_mean_m``,
    ``ped_deviation_max_m``, ``ped_delay_s``; all 0 under ``reaction="none"``); ``info["episode"]`` is left to
    Gymnasium's ``RecordEpisodeStatistics`` and SB3's ``Monitor``. Stepping after the end without ``reset`` raises
    ``RuntimeError``.

    ## Arguments

    ``gymnasium.make(id, config={...}, **kwargs)``: keywords override ``config`` (a mapping or a YAML
    path), which overrides the defaults of :class:`envs.config.CrowdNavConfig` (all keys listed
    there and in ``configs/env/default.yaml``). An unknown key or value lists the valid ones.

    | argument | default | meaning |
    |---|---|---|
    | ``predictor`` | per id | ``none``, ``cv``, ``mesrnn``, ``srnn``, ``vlstm``, ``oracle``, ``noisy_oracle``, or an object with ``forecast(history, mask)`` |
    | ``reaction`` | ``"none"`` | how pedestrians react to the robot: ``none``, ``pause``, ``orca``, ``social_force`` |
    | ``reaction_params`` | defaults | overrides of :class:`envs.reaction.ReactionParams` (trigger distance, bounds, model constants) |
    | ``crowd`` | ``"auto"`` | ``auto``, ``replay``, ``synthetic``, ``empty``, or a :class:`~crowdnav_mesrnn.data.Recording` |
    | ``split`` | ``"zara1"`` | leave-one-out split choosing the recordings |
    | ``part`` | ``"train"`` | ``train`` (four other scenes) or ``test`` (held-out scene) |
    | ``scenes`` | ``()`` | restrict to recordings or scene labels of the part |
    | ``kinematics`` | ``"holonomic"`` | or ``"unicycle"`` |
    | ``dt_s`` | 0.4 | control step, s |
    | ``num_pedestrians`` | 10 | K |
    | ``horizon_steps`` | 12 | H |
    | ``render_mode`` | None | ``"rgb_array"`` or ``"human"`` |
    | ... | | every field of :class:`envs.config.CrowdNavConfig` |

    ## Version History

    * v0: initial version (``env_revision`` 0, not recorded).
    * v0, ``env_revision`` 1: the pop-in rule (a pedestrian whose track begins on the robot is a contact-less,
      unperceived ghost until clear of it; ``popin_events`` in the episode metrics). Episodes in which a track
      begins within 0.7 m of the robot's centre change; every other episode is unchanged.
    * v0, ``env_revision`` 1 (unchanged): ``reaction`` and ``reaction_params``; the reset ``info`` names them and the
      episode metrics add the disturbance metrics (0 without a reaction). ``reaction="none"``, the default, gives the
      episodes of revision 1 bit for bit (observations, rewards and every earlier info key; tested), so results of
      revision 1 stay valid for it; a reaction model is named beside the revision (:func:`env_rules`).
    * v0, ``env_revision`` 1 (unchanged): ``forecast_uncertainty_method`` (``online`` thresholds) and
      ``forecast_samples`` (the optional ``forecast_samples`` key). Their defaults, ``split`` and 0, give the
      observations of revision 1 bit for bit (tested).
    * v0, ``env_revision`` 1 (unchanged), ``reaction_revision`` 2 of ``social_force``: a reacting pedestrian's
      relaxation acts on its deviation from the recording, so one on its track with no force walks as recorded
      (revision 1 lagged each recorded change of velocity and drifted off). ``social_force`` episodes change; the
      reset ``info`` and :func:`env_rules` name ``reaction_revision`` (:data:`envs.reaction.MODEL_REVISIONS`);
      ``none``, ``pause`` and ``orca`` are unchanged.
    """

    metadata: dict[str, Any] = {"render_modes": ["human", "rgb_array"], "render_fps": 2.5}  # noqa: RUF012

    def __init__(
        self,
        render_mode: str | None = None,
        config: Mapping[str, Any] | str | os.PathLike[str] | None = None,
        predictor: Any = _CONFIGURED,
        crowd: str | Recording | None = None,
        **kwargs: Any,
    ) -> None:
        overrides = dict(kwargs)
        predictor_obj: ForecastModel | None = None
        if predictor is None:
            raise ConfigError(
                "predictor=None is not a forecast source: pass 'none' for no forecasts, one of "
                f"{', '.join(predictors.names(plugins=False))}, or a predictor object (gymnasium.make(id) without "
                "predictor= uses the id's source; CrowdNavEnv() without it uses the config's)"
            )
        if isinstance(predictor, str):
            overrides["predictor"] = predictor
        elif predictor is not _CONFIGURED:
            predictor_obj = predictor
        crowd_obj: Recording | None = None
        if isinstance(crowd, str):
            overrides["crowd"] = crowd
        elif isinstance(crowd, Recording):
            crowd_obj = crowd
        elif crowd is not None:
            raise ConfigError(f"crowd must be one of auto, replay, synthetic, empty or a Recording, got {crowd!r}")
        self.config: CrowdNavConfig = config_from(config, overrides)
        cfg = self.config
        scene_named = names_scene(config, overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"unknown render_mode {render_mode!r}; valid: None, {', '.join(self.metadata['render_modes'])}"
            )
        with_pygame = importlib.util.find_spec("pygame") is not None
        if render_mode == "human" and not with_pygame:
            raise DependencyNotInstalled(HUMAN_NEEDS_PYGAME)
        self.render_mode = render_mode
        # without pygame only rgb_array is offered (drawn with Pillow), so checkers do not try a window
        modes = self.metadata["render_modes"] if with_pygame else ["rgb_array"]
        self.metadata = {**self.metadata, "render_fps": 1.0 / cfg.dt_s, "render_modes": modes}

        self.crowd_source: CrowdSource = CrowdSource("custom") if crowd_obj else crowd_source(cfg, scene_named)
        self.recordings = self._recordings(crowd_obj)
        self.forecaster: ForecastSource = make_forecast_source(cfg, [r.name for r in self.recordings], predictor_obj)
        self.predictor_name = self.forecaster.name
        self.with_forecasts = self.forecaster.active
        self.uncertainty: UncertaintySource | None = None
        self._episode_uncertainty: UncertaintySource | None = None
        self.samples: SampleSource | None = None
        if cfg.forecast_samples:
            self.samples = make_sample_source(cfg, [r.name for r in self.recordings], self.forecaster, predictor_obj)
        if cfg.forecast_uncertainty and self.with_forecasts:  # the none arm has no forecasts to be uncertain about
            self.uncertainty = make_uncertainty_source(cfg, self.forecaster, predictor_obj)
        self.reaction: str = cfg.reaction
        self._reactive: ReactiveWorld | None = None
        if cfg.reaction != "none":  # under none no crowd object exists: the replay is the world
            if self.forecaster.memory == "carried":
                raise ConfigError(
                    f"reaction {cfg.reaction!r} needs forecast_memory 'window': carried forecasts keep hidden states "
                    "from each pedestrian's first appearance in the recording, which reacting pedestrians change; only "
                    "window forecasts can be taken from the cache where the observed histories are the recorded ones"
                )
            self._reactive = ReactiveWorld(
                cfg.reaction, cfg.reaction_parameters, cfg.robot_radius_m, cfg.pedestrian_radius_m
            )
        self.sampler = EpisodeSampler(
            self.recordings,
            dt_s=cfg.dt_s,
            history_steps=OBS_LEN - 1,
            distance_m=(float(cfg.start_goal_distance_m[0]), float(cfg.start_goal_distance_m[1])),
            clearance_gap_m=cfg.start_clearance_m,
            robot_radius_m=cfg.robot_radius_m,
            ped_radius_m=cfg.pedestrian_radius_m,
            speed_mps=cfg.robot_pref_speed_mps,
            time_limit_factor=cfg.time_limit_factor,
            sensor_range_m=cfg.sensor_range_m,
            require_pedestrians=cfg.require_pedestrians,
            episode_time=cfg.episode_time,
            val_fraction=cfg.val_fraction,
        )
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = observation_space(cfg, self.with_forecasts)
        self._builder = ObservationBuilder(cfg, self.with_forecasts)
        self.world = World(cfg.robot_radius_m, cfg.pedestrian_radius_m)

        # constants of a step
        s = cfg.substeps
        self._substeps = s
        self._substep_s = cfg.dt_s / s
        # times of a step: substep boundaries before t_next, then t_next + h * dt_s (h = 0..H)
        self._sub_offsets = self._substep_s * np.arange(s)
        self._obs_offsets = cfg.dt_s * np.arange(cfg.horizon_steps + 1)
        self._r_sum = cfg.robot_radius_m + cfg.pedestrian_radius_m
        self._near_m = self._r_sum + max(cfg.discomfort_dist_m, 0.0) + cfg.robot_pref_speed_mps * cfg.dt_s + 0.05
        self._popin = PopInRule(self._r_sum + POPIN_MARGIN_M)

        self._timer = PhaseTimer(TIMING_KEYS)
        self._renderer: Any = None
        self.episode: Episode | None = None
        self._replay: Replay | None = None
        self._done = True
        self._started = False
        self._forecast_rng_parent: np.random.Generator | None = None
        self._forecast_rng: np.random.Generator | None = None

    # ------------------------------------------------------------------ construction helpers

    def _recordings(self, crowd_obj: Recording | None) -> list[Recording]:
        """The recordings episodes replay, from :attr:`crowd_source` (the embedded default says so), each with
        ``crowd_overlays`` time-shifted copies of itself overlaid when that is set (denser training crowds)."""
        recordings = self._crowd_recordings(crowd_obj)
        cfg = self.config
        if cfg.crowd_overlays and self.crowd_source.kind != "empty":  # config: part "train"/"val" only
            recordings = [
                overlay_recording(r, cfg.crowd_overlays, episode_time_window(r, cfg.episode_time, cfg.val_fraction))
                for r in recordings
            ]
        return recordings

    def _crowd_recordings(self, crowd_obj: Recording | None) -> list[Recording]:
        """The recordings of :attr:`crowd_source`, as recorded."""
        cfg = self.config
        kind = self.crowd_source.kind
        if crowd_obj is not None:
            return [crowd_obj]
        if kind == "empty":
            return [empty_recording()]
        if kind == "replay":
            names = resolve_scenes(cfg.scenes, episode_recordings(cfg.split, cfg.part), cfg.split, cfg.part)
            return [load_recording(n, "all_data", self.crowd_source.data_dir) for n in names]
        if self.crowd_source.embedded_default:
            warnings.warn(
                "CrowdNavEnv: no scene named and no ETH/UCY data found: replaying the embedded default, the project's "
                "synthetic social-force crowd. Naming a scene (split=, part=, scenes=) replays ETH/UCY and needs the "
                "data; crowd='synthetic' asks for this crowd without this warning. " + HOW_TO_GET_DATA,
                UserWarning,
                stacklevel=3,
            )
        return [self._synthetic()]

    @property
    def crowd_kind(self) -> str:
        """``replay``, ``synthetic``, ``empty`` or ``custom`` (:attr:`crowd_source`'s kind), with ``+N overlays``
        when ``crowd_overlays`` makes the crowd denser."""
        kind = self.crowd_source.kind
        overlays = self.config.crowd_overlays
        return f"{kind}+{overlays} overlays" if overlays and kind != "empty" else kind

    def _synthetic(self) -> Recording:
        cfg = self.config
        return synthetic_recording(
            cfg.synthetic_seed,
            cfg.synthetic_duration_s,
            cfg.synthetic_arrival_rate_per_s,
            (float(cfg.synthetic_area_m[0]), float(cfg.synthetic_area_m[1])),
        )

    # ------------------------------------------------------------------ public helpers

    @property
    def replay(self) -> Replay:
        """The current episode's replay (after ``reset``)."""
        if self._replay is None:
            raise RuntimeError("call reset() first")
        return self._replay

    def _tracked(self) -> Replay:
        """What the robot's tracker reads: the replay, or with a reaction model the record of where the pedestrians
        actually were at the annotation times (:class:`envs.reactive.ObservedReplay`)."""
        assert self._replay is not None
        if self._reactive is not None and self._reactive.observed is not None:
            return self._reactive.observed
        return self._replay

    @property
    def pedestrians(self) -> tuple[np.ndarray, np.ndarray]:
        """The world's pedestrians now: ``(N, 2)`` positions, metres, and ``(N,)`` presence (pop-in ghosts absent),
        rows of :attr:`replay`. With a reaction model, where they actually are; otherwise the recording."""
        if self._replay is None:
            raise RuntimeError("call reset() first")
        return self._last["positions"].copy(), self._last["present"].copy()

    def reaction_snapshot(self) -> ReactionSnapshot:
        """The reacting crowd now, to roll the reaction model forward for candidate robot paths
        (:meth:`envs.reactive.ReactionSnapshot.simulate`) without touching the episode: a privileged planner's hook
        (it reads the model and every recorded future; nothing of it enters an observation).

        Raises:
            RuntimeError: before ``reset``, or under ``reaction="none"`` (the pedestrians are the recording: their
                future is :attr:`replay`'s).
        """
        if self._reactive is None:
            raise RuntimeError(
                "reaction='none': the pedestrians are the recording; their future is env.replay.positions_at(times)"
            )
        if self._replay is None or self.episode is None:
            raise RuntimeError("call reset() first")
        k0, t0_s, dt_s, n, offsets = self._k0, self.episode.t0_s, self.config.dt_s, self._n, self._sub_offsets.copy()

        def substep_times(m: int) -> np.ndarray:
            return np.append(_grid_time(k0, t0_s, dt_s, n + m) + offsets, _grid_time(k0, t0_s, dt_s, n + m + 1))

        return ReactionSnapshot(
            self._reactive, self._popin, self._replay, substep_times, self.world.robot_position, self._substep_s
        )

    @property
    def time_s(self) -> float:
        """Current time, seconds since the recording's first frame."""
        return self._time(self._n)

    def _time(self, n: int) -> float:
        """Time of step ``n``: ``(k0 + n) * dt_s`` when t0 is on the dt grid (one float per grid time, so
        forecast caches are exact across episodes), else ``t0 + n * dt_s``."""
        assert self.episode is not None
        return _grid_time(self._k0, self.episode.t0_s, self.config.dt_s, n)

    @property
    def robot_position(self) -> np.ndarray:
        """``(2,)`` robot centre, metres."""
        return self.world.robot_position

    @property
    def steps_taken(self) -> int:
        """Control steps taken in the current episode (0 after ``reset``)."""
        return self._n

    def substep_times(self, n: int) -> np.ndarray:
        """``(S + 1,)`` times (seconds since the recording's first frame) of the physics substep ends of control
        step ``n`` of the episode, its start first: where the world places the pedestrians and checks contacts."""
        return np.append(self._time(n) + self._sub_offsets, self._time(n + 1))

    @property
    def observed_rows(self) -> np.ndarray:
        """Replay rows of the pedestrians in the last observation, in observation order."""
        return self._last["rows"].copy()

    @property
    def last_forecasts(self) -> np.ndarray | None:
        """``(m, H, 2)`` world-frame forecasts of the observed pedestrians (before clipping), or None."""
        fc = self._last["forecasts"]
        return None if fc is None else fc.copy()

    def true_future_forecasts(self) -> np.ndarray:
        """PRIVILEGED, for teachers only (no policy's observation carries it): the ``forecasts`` entry the last
        observation would hold under the oracle forecast (``predictor="oracle"``), whatever this environment's predictor
        -- the true future of the same perceived pedestrians, in the same rows, robot-relative frame, clipping and layout:
        ``(K, H, 2)`` float32 metres (``(K * H * 2,)`` with ``flatten_observation``), zeros in empty rows."""
        rows, perceived, positions, present, robot = self._last["truth"]
        truth = self._true_future(rows, perceived, positions, present).positions if len(rows) else None
        return self._builder.forecast_entry(robot, truth)

    def precompute_forecasts(self, recording: str | None = None) -> int:
        """Compute the forecast tables of the recordings (all by default) now rather than on first use.

        Returns:
            the number of annotation frames held (0 for sources without tables or without caching).
        """
        if not isinstance(self.forecaster, PredictorForecast) or not self.config.cache_forecasts:
            return 0
        recs = self.recordings if recording is None else [self.sampler.recording_named(recording)]
        return sum(self.forecaster.table(rec) for rec in recs)

    @property
    def timings(self) -> dict[str, float]:
        """Seconds spent per phase since the last :meth:`reset_timings` (exclusive of nested phases)."""
        return self._timer.totals

    def reset_timings(self) -> None:
        self._timer.reset()

    # ------------------------------------------------------------------ gym API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        if self._forecast_rng_parent is not self.np_random:
            # Forecast noise (noisy_oracle) draws from its own stream, spawned from the episode generator without
            # drawing from it: otherwise the noise would consume the generator the episodes are sampled from, and
            # the noisy arm would get other episodes than every other arm after the first (unseeded) reset.
            self._forecast_rng_parent = self.np_random
            try:
                self._forecast_rng = self.np_random.spawn(1)[0]
            except (TypeError, ValueError):  # a generator without a seed sequence
                self._forecast_rng = np.random.default_rng(int(self.np_random.integers(2**63)))
        ep = self._start_episode(reset_options(options, self.config.goal_tolerance_m))
        assert self._replay is not None
        self._popin.reset(self._replay, self._time(0), ep.start)
        pos, present = self._world_positions(self._time(0) + self._obs_offsets)
        present[0] &= ~self._popin.ghost
        obs, _ = self._observe(self._time(0), pos, present, ep.start)
        info = reset_info(ep, self.crowd_kind, self.predictor_name, self.reaction, self.config.reaction_params)
        if self.render_mode == "human":
            self.render()
        return obs, info

    @timed("reset")
    def _start_episode(self, opts: dict[str, Any]) -> Episode:
        """Draw the episode and set the world, the robot and the bookkeeping to its start."""
        cfg = self.config
        ep = self.sampler.sample(self.np_random, **opts)
        self.episode = ep
        history_s = (OBS_LEN - 1) * ep.recording.step_s
        self._replay = Replay(
            ep.recording, ep.t0_s - history_s, ep.t0_s + (ep.max_steps + 1 + cfg.horizon_steps) * cfg.dt_s
        )
        self.world.reset(ep.start)
        self._n = 0
        self._heading = math.atan2(ep.goal[1] - ep.start[1], ep.goal[0] - ep.start[0])
        self._velocity = np.zeros(2)
        self._forecast_log: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._metrics = EpisodeMetrics.of_episode(ep, cfg.dt_s, cfg.discomfort_dist_m, cfg.goal_tolerance_m)
        self._done = False
        self._started = True
        self._collided_last = False
        self._outcome: str | None = None  # drawn on the frames once the episode has ended
        self._touch_fault: dict[int, str] = {}
        self._trails: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=cfg.render_trail_steps)
        k0 = round(ep.t0_s / cfg.dt_s)
        self._k0: int | None = k0 if abs(ep.t0_s - k0 * cfg.dt_s) < 1e-9 else None
        if self._reactive is not None:
            self._reactive.reset(self._replay, self._time(0))
        if self.uncertainty is not None:  # the radii of this episode (a tracker per episode under "online")
            tracked = self._tracked()
            self._episode_uncertainty = self.uncertainty.for_episode(tracked, tracked.perceived_at(self._time(0)).index)
        return ep

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if self._done:
            raise RuntimeError("the episode has ended (terminated or truncated); call reset() before step()")
        velocities = self._command(self._parse_action(action))
        moved = self._physics(velocities)
        self._n += 1
        self._velocity = (moved.robot_after - moved.robot_before) / self.config.dt_s
        obs, sensed = self._observe(self.time_s, moved.positions, moved.present, moved.robot_after)
        reward, terminated, truncated, info = self._reward(moved, sensed)
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, truncated, info

    # ------------------------------------------------------------------ the phases of a step

    def _command(self, action: tuple[float, float]) -> list[tuple[float, float]]:
        """The robot's velocity (m/s) in each physics substep for an action, and its heading after the step."""
        cfg = self.config
        ax, ay = action
        s = self._substeps
        v_pref = cfg.robot_pref_speed_mps
        if cfg.kinematics == "holonomic":
            vx, vy = ax * v_pref, ay * v_pref
            speed = math.hypot(vx, vy)
            if speed > v_pref:
                vx, vy = vx * (v_pref / speed), vy * (v_pref / speed)
            if speed > 1e-9:
                self._heading = math.atan2(vy, vx)
            return [(vx, vy)] * s
        speed = ax * v_pref
        omega = ay * cfg.robot_max_turn_rate_radps
        h0, hs = self._heading, self._substep_s
        self._heading = math.remainder(h0 + omega * cfg.dt_s, 2 * math.pi)
        return [
            (speed * math.cos(h0 + omega * hs * (k + 0.5)), speed * math.sin(h0 + omega * hs * (k + 0.5)))
            for k in range(s)
        ]

    @timed("replay")
    def _world_positions(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        assert self._replay is not None
        return self._replay.positions_at(times_s)

    @timed("physics")
    def _physics(self, velocities: list[tuple[float, float]]) -> _Moved:
        """Move the robot through the crowd for one control step (pymunk substeps), with contacts and the smallest gap
        during the step; the pedestrians at the substep boundaries (replayed, or moved by the reaction model) and
        what each would do without the robot over the horizon after it (the recording)."""
        s = self._substeps
        # the substep ends of the step (as substep_times), then its end + h * dt_s
        pos_times = np.concatenate(
            [self._time(self._n) + self._sub_offsets, self._time(self._n + 1) + self._obs_offsets]
        )
        pos, present = self._world_positions(pos_times)
        robot0 = self.world.robot_position
        sub_pos = pos[: s + 1]
        # the pop-in rule: ghosts at the substep ends take no part in the step (no body, no contact, no gap)
        if self._reactive is None:
            ghost = self._popin.step(
                self._replay,
                pos_times[: s + 1],
                sub_pos,
                present[: s + 1],
                lambda: self._robot_path(robot0, velocities),
            )
            sub_present = present[: s + 1] if ghost is None else present[: s + 1] & ~ghost
        else:
            pos, present = self._react(pos_times, pos, present, self._robot_path(robot0, velocities))
            sub_pos, sub_present = pos[: s + 1], present[: s + 1]
            ghost = None  # applied by the reaction step
        d_sub = np.hypot(sub_pos[..., 0] - robot0[0], sub_pos[..., 1] - robot0[1])
        d_sub = np.where(sub_present, d_sub, np.inf)
        near = np.flatnonzero(d_sub.min(axis=0) < self._near_m) if d_sub.size else np.zeros(0, dtype=np.int64)
        ws = self.world.step(velocities, sub_pos[:, near], sub_present[:, near], near, self._substep_s)
        # smallest gap during the step (after its start): substeps for the pedestrians near the robot
        gap = math.inf
        if len(near):
            rp = ws.robot_positions[1:, None, :]
            dn = np.hypot(sub_pos[1:, near, 0] - rp[..., 0], sub_pos[1:, near, 1] - rp[..., 1])
            gap = float(np.where(sub_present[1:, near], dn, np.inf).min()) - self._r_sum
        for c in ws.contacts:
            self._touch_fault.setdefault(c.row, c.fault)
        self._touch_fault = {r: f for r, f in self._touch_fault.items() if r in ws.touching}
        fault = ws.contacts[0].fault if ws.contacts else next(iter(self._touch_fault.values()), None)
        collided = bool(ws.contacts) or bool(ws.touching)
        present_after = present[s:]
        if ghost is not None:
            present_after = present_after.copy()
            present_after[0] = sub_present[s]
        return _Moved(
            robot0, ws.robot_positions[-1], pos[s:], present_after, gap, collided, fault if collided else None,
            len(ws.contacts),
        )  # fmt: skip

    def _robot_path(self, robot0: np.ndarray, velocities: list[tuple[float, float]]) -> np.ndarray:
        """``(S + 1, 2)`` robot centre at the substep ends of a step commanding ``velocities``
        (:func:`envs.world.robot_path`)."""
        return robot_path(robot0, velocities, self._substep_s)

    @timed("reaction")
    def _react(
        self, times_s: np.ndarray, recorded: np.ndarray, present: np.ndarray, robot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pedestrians of a step under the reaction model: the pop-in rule on the recording (ghosts take no part
        in the model), the model over the substeps (:meth:`envs.reactive.ReactiveWorld.move`), then what each would
        do without the robot over the horizon (:meth:`envs.reactive.ReactiveWorld.future`).

        Args:
            times_s: ``(S + 1 + H,)`` the substep ends, then the step's end + ``h * dt_s``, seconds.
            recorded: ``(S + 1 + H, N, 2)`` the recording there, metres; present: ``(S + 1 + H, N)``.
            robot: ``(S + 1, 2)`` the robot's centre at the substep ends, metres.

        Returns:
            positions ``(S + 1 + H, N, 2)`` and presence (ghosts absent) at ``times_s``.
        """
        assert self._reactive is not None and self._replay is not None
        sub = slice(0, self._substeps + 1)
        ahead = slice(self._substeps + 1, None)
        ghost = self._popin.step(self._replay, times_s[sub], recorded[sub], present[sub], robot)
        motion = self._reactive.move(times_s[sub], recorded[sub], present[sub], ghost, robot, self._substep_s)
        future, future_present = self._reactive.future(self._replay, times_s[ahead], recorded[ahead], present[ahead])
        return np.concatenate([motion.positions, future]), np.concatenate([motion.present, future_present])

    @timed("reward")
    def _reward(self, moved: _Moved, sensed: _Sensed) -> tuple[float, bool, bool, dict[str, Any]]:
        """Reward components, termination, truncation, the step's info and the episode's metrics."""
        cfg = self.config
        ep = self.episode
        assert ep is not None
        before, after = moved.robot_before, moved.robot_after
        min_gap = min(moved.gap_m, sensed.gap_m)
        collided = moved.collided
        dist_before = math.hypot(ep.goal[0] - before[0], ep.goal[1] - before[1])
        dist_after = math.hypot(ep.goal[0] - after[0], ep.goal[1] - after[1])
        reached = dist_after <= cfg.goal_tolerance_m
        comps = reward_components(cfg, reached, collided, min_gap, dist_before, dist_after, sensed.intruding)
        reward = total_reward(comps)
        terminated = (collided and cfg.terminate_on_collision) or (reached and not collided)
        truncated = (not terminated) and self._n >= ep.max_steps
        step_m = math.hypot(after[0] - before[0], after[1] - before[1])
        self._metrics.update(
            reward, step_m, self._velocity, min_gap, sensed.intruding, moved.new_contacts, moved.fault, sensed.visible,
            sensed.ttc_s,
        )  # fmt: skip
        info: dict[str, Any] = {
            "time_s": round(self._n * cfg.dt_s, 9),
            "distance_to_goal_m": dist_after,
            "min_gap_m": None if math.isinf(min_gap) else min_gap,
            "collision": collided,
            "collision_fault": moved.fault,
            "reached_goal": reached and not collided,
            "reward_components": comps,
        }
        self._collided_last = collided
        if terminated or truncated:
            self._done = True
            if collided and cfg.terminate_on_collision:
                outcome = "collision"
            elif reached and not collided:
                outcome = "success"
            else:
                outcome = "timeout"
            self._outcome = outcome
            # info["episode"] belongs to Gymnasium's RecordEpisodeStatistics and SB3's Monitor
            self._forecast_errors()
            self._metrics.popin_events = self._popin.events
            info["episode_metrics"] = self._metrics.summary(outcome, self._n * cfg.dt_s, self.with_forecasts)
            info["episode_metrics"].update(UNDISTURBED if self._reactive is None else self._reactive.metrics.summary())
        return reward, terminated, truncated, info

    # ------------------------------------------------------------------ internals

    @staticmethod
    def _parse_action(action: Any) -> tuple[float, float]:
        """The action as two floats clipped to [-1, 1]; ``ValueError`` showing the value if malformed."""
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action must be 2 numbers in [-1, 1], got {action!r}") from None
        if a.shape != (2,):
            raise ValueError(f"action must have shape (2,), got shape {a.shape}: {action!r}")
        ax, ay = a.tolist()
        if not (math.isfinite(ax) and math.isfinite(ay)):
            raise ValueError(f"action must be finite, got {action!r}")
        return min(max(ax, -1.0), 1.0), min(max(ay, -1.0), 1.0)

    @timed("observation")
    def _observe(
        self, t_s: float, positions: np.ndarray, present: np.ndarray, robot: np.ndarray
    ) -> tuple[dict[str, np.ndarray], _Sensed]:
        """Perception at ``t_s``: what the robot perceives (causal) and its forecasts; plus, from the world, the
        gap at ``t_s`` and whether the robot intrudes on a pedestrian's true future path.

        Args:
            positions: ``(1 + H, N, 2)`` world (replay) metres at ``t_s + h * dt_s``; present: ``(1 + H, N)``.
            robot: ``(2,)`` robot position.
        """
        cfg = self.config
        assert self.episode is not None and self._replay is not None
        tracked = self._tracked()
        seen = tracked.perceived_at(t_s)
        # a pedestrian that was a pop-in ghost at the reported annotation is not perceived (causal: see envs.popin)
        perceived = seen.present & ~self._popin.dropped(seen.index, len(seen.present))
        rows, _ = nearest_visible(robot, seen.positions, perceived, cfg.sensor_range_m, cfg.num_pedestrians)
        p_now, pres_now = positions[0], present[0]
        gap = math.inf
        intruding = False
        if pres_now.any():
            d = np.hypot(p_now[pres_now, 0] - robot[0], p_now[pres_now, 1] - robot[1])
            gap = float(d.min()) - self._r_sum
            # intrusion: robot on a present pedestrian's true future path within the horizon
            dfut = np.hypot(positions[1:, :, 0] - robot[0], positions[1:, :, 1] - robot[1])
            intruding = bool(np.any((dfut < self._r_sum) & present[1:] & pres_now[None, :]))
        fc = self._forecast(t_s, rows, seen.positions, positions, present) if len(rows) else None
        unc = None
        if self._episode_uncertainty is not None and fc is not None:
            unc = self._episode_uncertainty.radius(tracked, t_s, rows, seen.age_s, seen.index)
        samples = None
        if self.samples is not None and fc is not None:
            samples = self.samples.draw(tracked, t_s, rows)
        time_left = 1.0 - self._n / self.episode.max_steps
        obs = self._builder.build(
            robot,
            self._velocity,
            self._heading,
            self.episode.goal,
            seen.positions[rows],
            seen.velocities[rows],
            fc,
            time_left,
            seen.age_s,
            unc,
            samples,
        )
        ttc = self._time_to_collision(robot, p_now, pres_now) if self._n > 0 else math.inf
        self._trails.append((p_now, pres_now))
        self._last = {
            "rows": rows,
            "forecasts": fc,
            "positions": p_now,
            "present": pres_now,
            "truth": (rows, seen.positions, positions, present, robot),  # for true_future_forecasts, computed on demand
        }
        return obs, _Sensed(gap, intruding, len(rows), ttc)

    def _time_to_collision(self, robot: np.ndarray, p_now: np.ndarray, pres_now: np.ndarray) -> float:
        """The smallest constant-velocity time to collision with a present pedestrian at the end of a step: the
        robot's velocity over the step, each pedestrian's over the same step in the world (0 for one that was not
        there at its start); see :func:`envs.rewards.min_time_to_collision`."""
        before, was = self._last["positions"], self._last["present"]
        both = (pres_now & was)[:, None]
        velocities = np.where(both, (p_now - np.where(both, before, p_now)) / self.config.dt_s, 0.0)
        return min_time_to_collision(robot, self._velocity, p_now, velocities, pres_now, self._r_sum)

    @timed("forecasts")
    def _forecast(
        self, t_s: float, rows: np.ndarray, perceived: np.ndarray, positions: np.ndarray, present: np.ndarray
    ) -> np.ndarray | None:
        """Forecasts ``(m, H, 2)`` of the perceived pedestrians ``rows`` (None without forecasts), kept for the
        episode's forecast errors (computed against the world's true future when the episode ends)."""
        if not self.with_forecasts:
            return None
        assert self._replay is not None and self._forecast_rng is not None
        truth = self._true_future(rows, perceived, positions, present) if self.forecaster.needs_truth else None
        reactive = self._reactive
        if (
            reactive is not None
            and reactive.observed is not None
            and isinstance(self.forecaster, PredictorForecast)
            and needs_observed(self.forecaster, reactive.observed, t_s)
        ):  # someone in the histories was off the recording: forecast from what the robot observed
            fc = observed_forecasts(self.forecaster, reactive.observed, t_s, rows, reactive.forecast_memo)
        else:
            fc = self.forecaster.forecast(self._replay, t_s, rows, truth, self._forecast_rng)
        if fc is not None:
            self._forecast_log.append((t_s, rows, fc))
        return fc

    @staticmethod
    def _true_future(rows: np.ndarray, perceived: np.ndarray, positions: np.ndarray, present: np.ndarray) -> TrueFuture:
        """The world's true future of the perceived pedestrians ``rows`` (``(m, H, 2)``, held at the last position once
        one has left): what the oracle forecasts. ``perceived``: ``(N, 2)`` perceived positions; ``positions``,
        ``present``: ``(1 + H, N, 2)``, ``(1 + H, N)`` of the world from now on."""
        future, valid = positions[1:, rows].transpose(1, 0, 2), present[1:, rows].T
        # a perceived pedestrian may have left the world since its annotation: hold the perceived position
        current = np.where(present[0, rows, None], positions[0, rows], perceived[rows])
        return TrueFuture(fill_forward(future, valid, current), valid)

    def _forecast_errors(self) -> None:
        """Displacement errors of every forecast of the episode against the pedestrians' true future, at once: the
        replay's; with a reaction model, where the pedestrians were in the world up to the episode's end, then what
        each would do without the robot from there (as the world's future rows: the recording, ``pause``'s
        time-shifted)."""
        if not self._forecast_log:
            return
        assert self._replay is not None
        cfg = self.config
        times = np.array([t for t, _, _ in self._forecast_log])[:, None] + cfg.dt_s * np.arange(
            1, cfg.horizon_steps + 1
        )
        steps = len(self._forecast_log)
        step_of = np.repeat(np.arange(steps), [len(r) for _, r, _ in self._forecast_log])
        rows = np.concatenate([r for _, r, _ in self._forecast_log])
        fc = np.concatenate([f for _, _, f in self._forecast_log])
        if self._reactive is None:  # the replay at the forecasts' rows only
            truth, valid = self._replay.rows_at(times[step_of], rows)
        else:
            pos, present = self._replay.positions_at(times.reshape(-1))
            pos = pos.reshape(steps, cfg.horizon_steps, -1, 2)
            present = present.reshape(steps, cfg.horizon_steps, -1)
            self._world_departures(times[:, 0] - cfg.dt_s, pos, present)
            truth, valid = pos[step_of, :, rows], present[step_of, :, rows]
        self._metrics.add_forecast_errors(np.hypot(*(fc - truth).transpose(2, 0, 1)), valid)
        self._forecast_log = []

    def _world_departures(self, made_s: np.ndarray, pos: np.ndarray, present: np.ndarray) -> None:
        """Where the world departed from the recording at the forecast times (in place): the forecast made at step
        ``n`` (time ``made_s``), at horizon ``h``, meets the world at step ``n + h`` while the episode ran, then the
        world's future rows at its last step.

        Args:
            made_s: ``(F,)`` times of the forecasts, seconds; pos: ``(F, H, N, 2)`` metres; present: ``(F, H, N)``.
        """
        assert self._reactive is not None
        cfg = self.config
        departures = self._reactive.departures
        ran = len(departures)
        made = np.rint((made_s - self._time(0)) / cfg.dt_s).astype(np.int64)
        step = made[:, None] + np.arange(1, cfg.horizon_steps + 1)[None, :]  # (F, H) the world's step
        k, h = np.nonzero(step <= ran)
        if len(k) and ran:  # every (forecast, horizon) gets the departures of its world step, in one assignment
            lengths = np.array([len(rows) for rows, _, _ in departures])
            first = np.cumsum(lengths) - lengths  # where each step's departures start in the concatenation
            met = step[k, h] - 1
            counts = lengths[met]
            pair = np.repeat(np.arange(len(k)), counts)
            src = np.repeat(first[met], counts) + np.arange(len(pair)) - np.repeat(np.cumsum(counts) - counts, counts)
            rows = np.concatenate([rows for rows, _, _ in departures])[src]
            pos[k[pair], h[pair], rows] = np.concatenate([where for _, where, _ in departures])[src]
            present[k[pair], h[pair], rows] = np.concatenate([here for _, _, here in departures])[src]
        rows, where, here = self._reactive.future_departures
        if len(rows):
            k, h = np.nonzero(step > ran)
            after = step[k, h] - ran - 1
            pos[k[:, None], h[:, None], rows[None, :]] = where[after]
            present[k[:, None], h[:, None], rows[None, :]] = here[after]

    # ------------------------------------------------------------------ rendering

    def render(self) -> np.ndarray | None:
        """Draw the current state (``rgb_array``: ``(H, W, 3)`` uint8; ``human``: a window; None without mode)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'")
            return None
        if self.episode is None:
            raise RuntimeError("call reset() before render()")
        from envs.rendering import Renderer, Scene

        cfg = self.config
        if self._renderer is None:
            self._renderer = Renderer(
                cfg.render_size_px, cfg.render_px_per_m, self.render_mode, self.metadata["render_fps"]
            )
        last = self._last
        pres = last["present"]
        visible = np.zeros(len(pres), dtype=bool)
        visible[last["rows"]] = True  # perceived; drawn where the world has them
        trails = []
        for row in np.flatnonzero(pres).tolist():
            pts = [p[row] for p, pr in self._trails if pr[row]]
            trails.append(np.array(pts))
        ep = self.episode
        status = f"scene {ep.recording.name}   t = {self._n * cfg.dt_s:4.1f} s   forecasts: {self.predictor_name}"
        scene = Scene(
            robot=self.world.robot_position,
            robot_radius_m=cfg.robot_radius_m,
            heading=self._heading,
            goal=ep.goal,
            goal_tolerance_m=cfg.goal_tolerance_m,
            pedestrians=last["positions"][pres],
            visible=visible[pres],
            ped_radius_m=cfg.pedestrian_radius_m,
            trails=trails,
            forecasts=last["forecasts"],
            sensor_range_m=cfg.sensor_range_m,
            center=self._view_center(),
            text=status,
            collided=self._collided_last,
            outcome=getattr(self, "_outcome", None),
            forecast_source=self.predictor_name if self.with_forecasts else None,
        )
        return self._renderer.draw(scene)

    def _view_center(self) -> np.ndarray:
        """Centre of the view: the start-goal midpoint, shifted just enough to keep the robot 1 m inside the scene's
        part of the frame (the frame less its title and legend strips)."""
        assert self.episode is not None
        cfg = self.config
        if getattr(self, "_view_episode", None) is not self.episode:
            self._view_episode = self.episode
            self._view = (self.episode.start + self.episode.goal) / 2
        size = self._renderer.layout.scene_size if self._renderer is not None else cfg.render_size_px
        half = np.array(size, dtype=np.float64) / 2 / cfg.render_px_per_m - 1.0
        half = np.maximum(half, 0.0)
        robot = self.world.robot_position
        self._view = np.clip(self._view, robot - half, robot + half)
        return self._view.copy()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
