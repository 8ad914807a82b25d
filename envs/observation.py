"""The observation: robot state, the K nearest pedestrians and (optionally) their forecasts.

Every array is freshly allocated at every step (callers may keep them). Positions are relative to
the robot's centre, axes of the world frame (no rotation).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium import spaces

from envs.config import CrowdNavConfig


def observation_space(cfg: CrowdNavConfig, with_forecasts: bool) -> spaces.Dict:
    """The ``Dict`` space (``pedestrians`` and ``forecasts`` flattened row-major if ``flatten_observation``).

    Keys:
        ``robot``: ``(4,)`` to ``(7,)`` float32: goal offset x, y (m, clipped to ±max_goal_offset_m),
        velocity x, y (m/s), for the unicycle cos and sin of the heading, with ``observe_time_left``
        the fraction of the time limit left (in [0, 1]), and with ``observe_perception_age`` the age of
        the perceived annotation (s, in [0, 1]) last.
        ``pedestrians``: ``(K, 4)`` float32: position relative to the robot (m) and velocity relative
        to the robot's (m/s) of the K nearest pedestrians within the sensor range, nearest first;
        zero rows where the mask is 0. Both as perceived at t: the latest annotation at or before t
        (see :meth:`envs.replay.Replay.perceived_at`).
        ``mask``: ``(K,)`` int8 MultiBinary: 1 where a row holds a pedestrian.
        ``forecasts`` (unless the predictor is ``none``): ``(K, H, 2)`` float32 forecast positions
        relative to the robot's current position (m) at ``t + h * dt_s``, h = 1..H.
        ``forecast_uncertainty`` (with ``forecast_uncertainty`` and forecasts): ``(K, H)`` float32 radius (m) of
        the disc around each forecast position holding the true one with probability ``forecast_uncertainty_level``
        (0 on empty rows; :mod:`envs.forecasting.uncertainty`).
        ``forecast_samples`` (with ``forecast_samples`` = S > 0 and forecasts): ``(K, S, H, 2)`` float32 sampled future
        positions relative to the robot's current position (m) at ``t + h * dt_s`` (0 on empty rows;
        :mod:`envs.forecasting.samples`).
    """
    k, h = cfg.num_pedestrians, cfg.horizon_steps
    v = cfg.robot_pref_speed_mps
    g = cfg.max_goal_offset_m
    robot_hi = [g, g, v, v] + ([1.0, 1.0] if cfg.kinematics == "unicycle" else [])
    robot_lo = [-x for x in robot_hi]
    for flag in (cfg.observe_time_left, cfg.observe_perception_age):
        if flag:
            robot_lo.append(0.0)
            robot_hi.append(1.0)
    robot_lo_arr = np.array(robot_lo, dtype=np.float32)
    robot_hi_arr = np.array(robot_hi, dtype=np.float32)
    rel_speed = cfg.max_obs_speed_mps + v
    ped_hi = np.tile(np.array([cfg.sensor_range_m, cfg.sensor_range_m, rel_speed, rel_speed], dtype=np.float32), (k, 1))
    fc_hi = np.full((k, h, 2), forecast_bound_m(cfg), dtype=np.float32)
    if cfg.flatten_observation:
        ped_hi, fc_hi = ped_hi.reshape(-1), fc_hi.reshape(-1)
    out: dict[str, spaces.Space[Any]] = {
        "robot": spaces.Box(robot_lo_arr, robot_hi_arr, dtype=np.float32),
        "pedestrians": spaces.Box(-ped_hi, ped_hi, dtype=np.float32),
        "mask": spaces.MultiBinary(k),
    }
    if with_forecasts:
        out["forecasts"] = spaces.Box(-fc_hi, fc_hi, dtype=np.float32)
        if cfg.forecast_uncertainty:
            unc_hi = np.full((k, h), forecast_bound_m(cfg), dtype=np.float32)
            if cfg.flatten_observation:
                unc_hi = unc_hi.reshape(-1)
            out["forecast_uncertainty"] = spaces.Box(np.zeros_like(unc_hi), unc_hi, dtype=np.float32)
        if cfg.forecast_samples:
            smp_hi = np.full((k, cfg.forecast_samples, h, 2), forecast_bound_m(cfg), dtype=np.float32)
            if cfg.flatten_observation:
                smp_hi = smp_hi.reshape(-1)
            out["forecast_samples"] = spaces.Box(-smp_hi, smp_hi, dtype=np.float32)
    return spaces.Dict(out)


def structured(obs: dict[str, np.ndarray], num_pedestrians: int, horizon_steps: int) -> dict[str, np.ndarray]:
    """Views of an observation (single or batched ``(B, ...)``) with ``pedestrians`` as ``(..., K, 4)``,
    ``forecasts`` as ``(..., K, H, 2)`` and ``forecast_samples`` as ``(..., K, S, H, 2)``, whether or not it was
    flattened."""
    out = dict(obs)
    lead = obs["mask"].shape[:-1]
    out["pedestrians"] = obs["pedestrians"].reshape(*lead, num_pedestrians, 4)
    if "forecasts" in obs:
        out["forecasts"] = obs["forecasts"].reshape(*lead, num_pedestrians, horizon_steps, 2)
    if "forecast_uncertainty" in obs:
        out["forecast_uncertainty"] = obs["forecast_uncertainty"].reshape(*lead, num_pedestrians, horizon_steps)
    if "forecast_samples" in obs:
        out["forecast_samples"] = obs["forecast_samples"].reshape(*lead, num_pedestrians, -1, horizon_steps, 2)
    return out


def forecast_bound_m(cfg: CrowdNavConfig) -> float:
    """Forecast offsets are clipped to ±(sensor range + max_obs_speed x horizon), metres."""
    return cfg.sensor_range_m + cfg.max_obs_speed_mps * cfg.horizon_s


def nearest_visible(
    robot_position: np.ndarray, positions: np.ndarray, present: np.ndarray, sensor_range_m: float, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the ``k`` nearest present pedestrians within the sensor range, nearest first.

    Args:
        robot_position: ``(2,)`` metres.
        positions: ``(N, 2)`` metres.
        present: ``(N,)`` bool.
        sensor_range_m: centre-distance range, metres.
        k: number of rows at most.

    Returns:
        ``(rows (m,), distances (N,))`` with ``m <= k`` and the centre distance of every pedestrian
        (``inf`` where absent).
    """
    d = np.hypot(positions[:, 0] - robot_position[0], positions[:, 1] - robot_position[1])
    d = np.where(present, d, np.inf)
    cand = np.flatnonzero(d <= sensor_range_m)
    if len(cand) > k:
        cand = cand[np.argpartition(d[cand], k - 1)[:k]]
    return cand[np.argsort(d[cand], kind="stable")], d


def _clip(x: np.ndarray, bound: float) -> np.ndarray:
    """``x`` clipped to ``[-bound, bound]`` in place (faster than ``np.clip`` on small arrays)."""
    np.minimum(x, bound, out=x)
    np.maximum(x, -bound, out=x)
    return x


class ObservationBuilder:
    """Builds observation dicts (fresh arrays each call) for a configuration."""

    def __init__(self, cfg: CrowdNavConfig, with_forecasts: bool) -> None:
        self.k = cfg.num_pedestrians
        self.h = cfg.horizon_steps
        self.with_forecasts = with_forecasts
        self.unicycle = cfg.kinematics == "unicycle"
        self.time_left = cfg.observe_time_left
        self.age = cfg.observe_perception_age
        self.robot_size = 4 + 2 * self.unicycle + int(self.time_left) + int(self.age)
        self.goal_clip = cfg.max_goal_offset_m
        self.speed = cfg.robot_pref_speed_mps
        self.rel_speed = cfg.max_obs_speed_mps + cfg.robot_pref_speed_mps
        self.max_ped_speed = cfg.max_obs_speed_mps
        self.sensor = cfg.sensor_range_m
        self.fc_bound = forecast_bound_m(cfg)
        self.flat = cfg.flatten_observation
        self.with_uncertainty = with_forecasts and cfg.forecast_uncertainty
        self.samples = cfg.forecast_samples if with_forecasts else 0

    def forecast_entry(self, robot_position: np.ndarray, forecasts: np.ndarray | None) -> np.ndarray:
        """The observation's ``forecasts`` entry: ``(K, H, 2)`` float32 (flat with ``flatten_observation``), the world
        forecasts ``(m, H, 2)`` of the ``m`` visible pedestrians relative to ``robot_position`` ``(2,)`` and clipped,
        zeros in the empty rows (all zeros for None)."""
        fc = np.zeros((self.k, self.h, 2), dtype=np.float32)
        if forecasts is not None and len(forecasts):
            fc[: len(forecasts)] = _clip(forecasts - robot_position, self.fc_bound)
        return fc.reshape(-1) if self.flat else fc

    def build(
        self,
        robot_position: np.ndarray,
        robot_velocity: np.ndarray,
        heading: float,
        goal: np.ndarray,
        ped_positions: np.ndarray,
        ped_velocities: np.ndarray,
        forecasts: np.ndarray | None,
        time_left: float = 1.0,
        perception_age_s: float = 0.0,
        uncertainty: np.ndarray | None = None,
        samples: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """One observation.

        Args:
            robot_position: ``(2,)`` metres.
            robot_velocity: ``(2,)`` m/s.
            heading: radians (used for the unicycle).
            goal: ``(2,)`` metres.
            ped_positions: ``(m, 2)`` world positions of the visible pedestrians, nearest first.
            ped_velocities: ``(m, 2)`` their world velocities, m/s.
            forecasts: ``(m, H, 2)`` world forecast positions, or None.
            time_left: fraction of the time limit left (used with ``observe_time_left``).
            perception_age_s: age of the perceived annotation, s (used with ``observe_perception_age``).
            uncertainty: ``(m, H)`` radii of the forecasts' regions, metres (used with ``forecast_uncertainty``).
            samples: ``(m, S, H, 2)`` world positions of sampled futures (used with ``forecast_samples``).
        """
        m = len(ped_positions)
        robot = np.empty(self.robot_size, dtype=np.float32)
        g, v = self.goal_clip, self.speed
        robot[0] = min(max(goal[0] - robot_position[0], -g), g)
        robot[1] = min(max(goal[1] - robot_position[1], -g), g)
        robot[2] = min(max(robot_velocity[0], -v), v)
        robot[3] = min(max(robot_velocity[1], -v), v)
        if self.unicycle:
            robot[4] = math.cos(heading)
            robot[5] = math.sin(heading)
        extra = 4 + 2 * self.unicycle
        if self.time_left:
            robot[extra] = min(max(time_left, 0.0), 1.0)
            extra += 1
        if self.age:
            robot[extra] = min(max(perception_age_s, 0.0), 1.0)
        peds = np.zeros((self.k, 4), dtype=np.float32)
        mask = np.zeros(self.k, dtype=np.int8)
        if m:
            peds[:m, 0:2] = _clip(ped_positions - robot_position, self.sensor)
            peds[:m, 2:4] = _clip(_clip(ped_velocities, self.max_ped_speed) - robot_velocity, self.rel_speed)
            mask[:m] = 1
        obs = {"robot": robot, "pedestrians": peds.reshape(-1) if self.flat else peds, "mask": mask}
        if self.with_forecasts:
            obs["forecasts"] = self.forecast_entry(robot_position, forecasts if m else None)
        if self.with_uncertainty:
            unc = np.zeros((self.k, self.h), dtype=np.float32)
            if m and uncertainty is not None:
                unc[:m] = np.clip(uncertainty, 0.0, self.fc_bound)
            obs["forecast_uncertainty"] = unc.reshape(-1) if self.flat else unc
        if self.samples:
            smp = np.zeros((self.k, self.samples, self.h, 2), dtype=np.float32)
            if m and samples is not None:
                smp[:m] = _clip(samples - robot_position, self.fc_bound)
            obs["forecast_samples"] = smp.reshape(-1) if self.flat else smp
        return obs
