"""What every planner shares: the ``predict`` plumbing, velocities turned into actions, the straight-to-goal policy.

A planner is built from the environment's configuration (:func:`as_env_config`), implements ``act(batch) ->
actions (B, 2)`` on a batched observation, and gets SB3's ``predict`` from :class:`_Planner`: a single observation
or a batch (a leading dimension on every key) in, ``(actions, None)`` out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from envs.config import CrowdNavConfig, config_from
from envs.observation import structured


def as_env_config(env_config: CrowdNavConfig | Mapping[str, Any] | None) -> CrowdNavConfig:
    """The environment configuration itself, or one built (validated) from a mapping of settings."""
    if isinstance(env_config, CrowdNavConfig):
        return env_config
    return config_from(dict(env_config or {}), {})


def velocities_to_actions(velocity: np.ndarray, robot: np.ndarray, cfg: CrowdNavConfig) -> np.ndarray:
    """Actions ``(B, 2)`` float32 commanding world-frame velocities ``(B, 2)`` m/s.

    Holonomic: the velocity divided by the preferred speed. Unicycle: turn towards it (at most the
    maximum turn rate over one step; heading from ``robot[:, 4:6]``) and drive at its speed times the
    cosine of the heading error (never backwards).
    """
    v = cfg.robot_pref_speed_mps
    velocity = np.asarray(velocity, dtype=np.float64)
    if cfg.kinematics == "holonomic":
        return np.clip(velocity / v, -1.0, 1.0).astype(np.float32)
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    heading = np.arctan2(robot[:, 5].astype(np.float64), robot[:, 4].astype(np.float64))
    raw = np.arctan2(velocity[:, 1], velocity[:, 0]) - heading
    err = np.array([math.remainder(x, 2 * math.pi) for x in raw.tolist()], dtype=np.float64)  # exact wrap to [-pi, pi]
    turn = np.clip(err / (cfg.robot_max_turn_rate_radps * cfg.dt_s), -1.0, 1.0)
    fwd = np.minimum(speed / v * np.maximum(np.cos(err), 0.0), 1.0)
    out = np.stack([fwd, turn], axis=1)
    out[speed < 1e-9] = 0.0
    return out.astype(np.float32)


def velocity_to_action(velocity: np.ndarray, obs_robot: np.ndarray, cfg: CrowdNavConfig) -> np.ndarray:
    """The action ``(2,)`` commanding one world-frame ``velocity`` ``(2,)`` m/s (see :func:`velocities_to_actions`)."""
    return velocities_to_actions(np.asarray(velocity)[None], np.asarray(obs_robot)[None], cfg)[0]


def _goal_velocity(robot: np.ndarray, cfg: CrowdNavConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Goal offsets ``(B, 2)``, distances ``(B,)`` and speed caps ``(B,)`` (preferred speed, or arriving in one step)."""
    offset = robot[:, :2].astype(np.float64)
    dist = np.hypot(offset[:, 0], offset[:, 1])
    cap = np.minimum(cfg.robot_pref_speed_mps, dist / cfg.dt_s)
    return offset, dist, cap


def go_to_goal(obs: Mapping[str, np.ndarray], cfg: CrowdNavConfig) -> np.ndarray:
    """Straight to the goal at the preferred speed, arriving in one step when closer than a step.

    Args:
        obs: one observation (unbatched).
        cfg: the environment's configuration.

    Returns:
        the action ``(2,)`` float32.
    """
    return StraightToGoal(cfg).predict(obs)[0]


def region_radii(obs: Mapping[str, np.ndarray], cfg: CrowdNavConfig, steps: int, uncertainty: bool) -> np.ndarray:
    """Radii of the regions a planner keeps clear of around the forecast positions of the first ``steps`` steps.

    The planners' ``uncertainty`` option (:class:`SamplingPlanner`, :class:`SearchPlanner`): with it, the radius of
    each forecast step's uncertainty region -- the observation key ``forecast_uncertainty`` of an environment made
    with ``forecast_uncertainty=True`` (a calibrated disc, :mod:`envs.forecasting.uncertainty`) --; without it, 0 (points).

    Args:
        obs: a batched observation (flat or structured).
        cfg: the environment's configuration.
        steps: forecast steps wanted (at most H).
        uncertainty: the planner's option.

    Returns:
        ``(B, K, steps)`` float64 metres.

    Raises:
        ValueError: ``uncertainty`` without the observation key.
    """
    b = np.shape(obs["mask"])[0]
    if not uncertainty:
        return np.zeros((b, cfg.num_pedestrians, steps))
    if "forecast_uncertainty" not in obs:
        raise ValueError(
            "the planner's uncertainty option needs the observation key 'forecast_uncertainty' (make the "
            f"environment with forecast_uncertainty=True and forecasts); got keys {sorted(obs)}"
        )
    o = structured(dict(obs), cfg.num_pedestrians, cfg.horizon_steps)
    return o["forecast_uncertainty"][:, :, :steps].astype(np.float64)


def _fractions_and_headings(headings_deg: Sequence[float], speed_fractions: Sequence[float]) -> tuple[np.ndarray, ...]:
    """Checked ``(headings (Hd,) radians, fractions (F,))``; ``ValueError`` naming the bad option."""
    angles = np.deg2rad(np.asarray(headings_deg, dtype=np.float64).reshape(-1))
    speeds = np.asarray(speed_fractions, dtype=np.float64).reshape(-1)
    if not len(angles) or not len(speeds):
        raise ValueError("headings_deg and speed_fractions must not be empty")
    if not np.all((speeds > 0) & (speeds <= 1)):
        raise ValueError(f"speed_fractions must lie in (0, 1], got {speeds.tolist()!r}")
    return angles, speeds


class _Planner:
    """Shared ``predict`` plumbing: batch a single observation, call :meth:`act`, unbatch."""

    def __init__(self, env_config: CrowdNavConfig | Mapping[str, Any] | None = None) -> None:
        self.cfg = as_env_config(env_config)

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def predict(
        self,
        obs: Mapping[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """Actions for one observation (``(2,)``) or a batch (every key with a leading ``B``; ``(B, 2)``).

        ``state``, ``episode_start`` and ``deterministic`` exist for SB3 compatibility (planners are
        stateless and deterministic).
        """
        if "mask" not in obs or "robot" not in obs:
            raise ValueError(f"observation must hold 'robot' and 'mask' keys, got {sorted(obs)}")
        single = np.ndim(obs["mask"]) == 1
        batch = {k: np.asarray(v)[None] if single else np.asarray(v) for k, v in obs.items()}
        actions = self.act(batch)
        return (actions[0] if single else actions), None

    def __call__(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        return self.predict(obs)[0]


class StraightToGoal(_Planner):
    """Straight to the goal at the preferred speed, ignoring pedestrians.

    Args:
        env_config: the environment's configuration (a :class:`~envs.config.CrowdNavConfig` or a mapping).
    """

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        robot = obs["robot"]
        offset, dist, cap = _goal_velocity(robot, self.cfg)
        scale = np.divide(cap, dist, out=np.zeros_like(dist), where=dist >= 1e-9)
        return velocities_to_actions(offset * scale[:, None], robot, self.cfg)
