"""Non-learned policies with Stable-Baselines3's ``predict`` interface.

- :class:`StraightToGoal`: straight to the goal at the preferred speed, slowing down to stop on it.
- :class:`SamplingPlanner`: scores candidate velocities (headings around the goal direction times
  speeds, plus standing still) against the future positions of the observed pedestrians — the
  forecasts the observation carries, or constant-velocity extrapolations of their observed
  velocities when it has none (the ``none`` arm) — and takes the fastest progress that stays clear.

Both accept a single observation dict or a batched one (a leading dimension on every key) and
return ``(actions, None)`` like an SB3 model, so evaluation treats planners and learned policies
alike. The candidate scoring is vectorised over the batch.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np

from envs.config import CrowdNavConfig, config_from
from envs.observation import structured

#: Names accepted by :func:`make_planner`.
PLANNERS: Final[tuple[str, ...]] = ("straight", "planner")
#: Default candidate headings relative to the goal direction, degrees (9 headings).
DEFAULT_HEADINGS_DEG: Final[tuple[float, ...]] = (0.0, 20.0, -20.0, 40.0, -40.0, 60.0, -60.0, 90.0, -90.0)
#: Default candidate speeds as fractions of the speed cap (4 speeds; with standing still: 9 x 4 + 1 = 37 candidates).
DEFAULT_SPEED_FRACTIONS: Final[tuple[float, ...]] = (1.0, 0.75, 0.5, 0.25)


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


class SamplingPlanner(_Planner):
    """Goes to the goal, but checks candidate velocities against the observed pedestrians' futures.

    Candidates are every heading in ``headings_deg`` (relative to the goal direction) at every
    speed in ``speed_fractions`` (of the speed cap: the preferred speed, or what reaches the goal in
    one step), plus standing still — 9 x 4 + 1 = 37 by default. A candidate is clear when, over the
    first ``lookahead_steps`` forecast steps, the robot moving at it stays at least the sum of radii
    plus ``margin_m`` from every future position. The future positions are the observation's
    forecasts if it has them, else constant-velocity extrapolations of the observed velocities.
    The planner takes the clear candidate with the most progress towards the goal; it stands still
    when standing is clear and no clear candidate makes progress, or when no candidate is clear but
    standing is; otherwise it takes the candidate with the largest gap.

    Args:
        env_config: the environment's configuration (a :class:`~envs.config.CrowdNavConfig` or a mapping).
        lookahead_steps: forecast steps (of ``dt_s``) a candidate is checked over (at most H).
        margin_m: required gap beyond touching, metres.
        headings_deg: candidate headings relative to the goal direction, degrees.
        speed_fractions: candidate speeds as fractions of the speed cap, in (0, 1].
        uncertainty: require clearance of each forecast step's uncertainty region instead of its point: the
            gap is measured from the edge of the disc of radius ``forecast_uncertainty`` (the observation key of
            ``forecast_uncertainty=True``, a calibrated region) around the forecast position. Needs that key.
    """

    def __init__(
        self,
        env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
        lookahead_steps: int = 6,
        margin_m: float = 0.2,
        headings_deg: Sequence[float] = DEFAULT_HEADINGS_DEG,
        speed_fractions: Sequence[float] = DEFAULT_SPEED_FRACTIONS,
        uncertainty: bool = False,
    ) -> None:
        super().__init__(env_config)
        self.uncertainty = bool(uncertainty)
        cfg = self.cfg
        if lookahead_steps < 1:
            raise ValueError(f"lookahead_steps must be >= 1, got {lookahead_steps!r}")
        angles = np.deg2rad(np.asarray(headings_deg, dtype=np.float64).reshape(-1))
        speeds = np.asarray(speed_fractions, dtype=np.float64).reshape(-1)
        if not len(angles) or not len(speeds):
            raise ValueError("headings_deg and speed_fractions must not be empty")
        if not np.all((speeds > 0) & (speeds <= 1)):
            raise ValueError(f"speed_fractions must lie in (0, 1], got {speeds.tolist()!r}")
        self.lookahead = min(int(lookahead_steps), cfg.horizon_steps)
        self.clear_m = cfg.robot_radius_m + cfg.pedestrian_radius_m + float(margin_m)
        self._angles = np.repeat(angles, len(speeds))  # (C,) heading-major, as listed
        self._fractions = np.tile(speeds, len(angles))  # (C,)
        self._steps = cfg.dt_s * np.arange(1, self.lookahead + 1)  # (L,) seconds

    @property
    def num_candidates(self) -> int:
        """Candidate velocities including standing still."""
        return len(self._angles) + 1

    def futures(self, obs: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Future positions of the observation rows relative to the robot.

        Args:
            obs: a batched observation.

        Returns:
            ``(positions (B, K, L, 2) metres, mask (B, K) bool)``.
        """
        cfg = self.cfg
        o = structured(dict(obs), cfg.num_pedestrians, cfg.horizon_steps)
        mask = o["mask"].astype(bool)
        if "forecasts" in o:
            return o["forecasts"][:, :, : self.lookahead].astype(np.float64), mask
        peds = o["pedestrians"].astype(np.float64)
        ped_vel = peds[..., 2:4] + o["robot"][:, None, 2:4].astype(np.float64)  # (B, K, 2) world velocity
        fut = peds[:, :, None, :2] + ped_vel[:, :, None, :] * self._steps[None, None, :, None]
        return fut, mask

    def future_radii(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """``(B, K, L)`` radii (m) of the regions the robot must stay clear of around the future positions of
        :meth:`futures`: the observation's ``forecast_uncertainty`` with ``uncertainty=True``, else 0 (points)."""
        cfg = self.cfg
        b = np.shape(obs["mask"])[0]
        if not self.uncertainty:
            return np.zeros((b, cfg.num_pedestrians, self.lookahead))
        if "forecast_uncertainty" not in obs:
            raise ValueError(
                "the planner's uncertainty option needs the observation key 'forecast_uncertainty' (make the "
                f"environment with forecast_uncertainty=True and forecasts); got keys {sorted(obs)}"
            )
        o = structured(dict(obs), cfg.num_pedestrians, cfg.horizon_steps)
        return o["forecast_uncertainty"][:, :, : self.lookahead].astype(np.float64)

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        cfg = self.cfg
        robot = obs["robot"]
        offset, dist, cap = _goal_velocity(robot, cfg)
        goal_dir = np.arctan2(offset[:, 1], offset[:, 0])  # (B,)
        theta = goal_dir[:, None] + self._angles[None, :]  # (B, C)
        speed = self._fractions[None, :] * cap[:, None]  # (B, C)
        vel = np.stack([speed * np.cos(theta), speed * np.sin(theta)], axis=-1)  # (B, C, 2)
        fut, mask = self.futures(obs)  # (B, K, L, 2), (B, K)
        radii = self.future_radii(obs)  # (B, K, L): 0, or the uncertainty regions' radii
        path = vel[:, :, None, :] * self._steps[None, None, :, None]  # (B, C, L, 2)
        diff = path[:, :, None] - fut[:, None]  # (B, C, K, L, 2)
        dist_ck = (np.sqrt(np.einsum("bckld,bckld->bckl", diff, diff)) - radii[:, None]).min(axis=3)  # (B, C, K)
        gap = np.where(mask[:, None, :], dist_ck, np.inf).min(axis=2)  # (B, C)
        stop_d = (np.hypot(fut[..., 0], fut[..., 1]) - radii).min(axis=2)  # (B, K)
        stop_gap = np.where(mask, stop_d, np.inf).min(axis=1)  # (B,)
        progress = speed * np.cos(self._angles)[None, :]  # (B, C)
        ok = gap >= self.clear_m
        any_ok = ok.any(axis=1)
        best_ok = np.argmax(np.where(ok, progress, -np.inf), axis=1)
        best_gap = np.argmax(gap, axis=1)
        rows = np.arange(len(robot))
        choice = np.where(any_ok, best_ok, best_gap)
        chosen = vel[rows, choice]  # (B, 2)
        stop_clear = stop_gap >= self.clear_m
        stand = np.where(any_ok, stop_clear & (progress[rows, best_ok] <= 0), stop_clear)
        stand |= dist < 1e-9
        chosen[stand] = 0.0
        # no pedestrian: the first candidate (straight at the goal), as without a conflict
        chosen = np.where((~mask.any(axis=1))[:, None] & (dist >= 1e-9)[:, None], vel[:, 0], chosen)
        return velocities_to_actions(chosen, robot, cfg)


def make_planner(name: str, env_config: CrowdNavConfig | Mapping[str, Any] | None = None, **kwargs: Any) -> _Planner:
    """A planner by name: ``"straight"`` (:class:`StraightToGoal`) or ``"planner"`` (:class:`SamplingPlanner`,
    ``kwargs`` passed on)."""
    if name == "straight":
        if kwargs:
            raise ValueError(f"the straight-to-goal policy takes no options, got {sorted(kwargs)}")
        return StraightToGoal(env_config)
    if name == "planner":
        return SamplingPlanner(env_config, **kwargs)
    raise ValueError(f"unknown planner {name!r}; valid: {', '.join(PLANNERS)}")
