"""Scripted (non-learning) policies acting on the environment's observation.

- :func:`go_to_goal`: straight to the goal at the preferred speed, slowing down to stop on it.
- :class:`ForecastAwarePolicy`: goes to the goal, but checks candidate velocities (headings within
  ±90° of the goal direction, four speeds, and standing still) against the observed pedestrians'
  forecasts — or constant-velocity extrapolations of their observed velocities when the
  observation holds no forecasts — and takes the fastest progress that stays clear.
"""

from __future__ import annotations

import math

import numpy as np

from envs.config import CrowdNavConfig
from envs.observation import structured


def _wrap(angle: float) -> float:
    return math.remainder(angle, 2 * math.pi)


def velocity_to_action(velocity: np.ndarray, obs_robot: np.ndarray, cfg: CrowdNavConfig) -> np.ndarray:
    """The action that commands a world-frame ``velocity`` ``(2,)`` m/s.

    Holonomic: the velocity scaled by the preferred speed. Unicycle: turn towards it (at most the
    maximum turn rate over one step) and drive at its speed times the cosine of the heading error.
    """
    v = cfg.robot_pref_speed_mps
    if cfg.kinematics == "holonomic":
        return np.clip(np.asarray(velocity, dtype=np.float64) / v, -1.0, 1.0).astype(np.float32)
    speed = float(np.hypot(velocity[0], velocity[1]))
    heading = math.atan2(float(obs_robot[5]), float(obs_robot[4]))
    if speed < 1e-9:
        return np.zeros(2, dtype=np.float32)
    err = _wrap(math.atan2(float(velocity[1]), float(velocity[0])) - heading)
    turn = float(np.clip(err / (cfg.robot_max_turn_rate_radps * cfg.dt_s), -1.0, 1.0))
    fwd = speed / v * max(math.cos(err), 0.0)
    return np.array([min(fwd, 1.0), turn], dtype=np.float32)


def go_to_goal(obs: dict[str, np.ndarray], cfg: CrowdNavConfig) -> np.ndarray:
    """Straight to the goal at the preferred speed, arriving in one step when closer than a step."""
    offset = np.asarray(obs["robot"][:2], dtype=np.float64)
    dist = float(np.hypot(offset[0], offset[1]))
    if dist < 1e-9:
        return np.zeros(2, dtype=np.float32)
    speed = min(cfg.robot_pref_speed_mps, dist / cfg.dt_s)
    return velocity_to_action(offset / dist * speed, obs["robot"], cfg)


class ForecastAwarePolicy:
    """Straight to the goal, slowing down or swerving for forecast conflicts.

    Args:
        cfg: the environment's configuration.
        lookahead_steps: how many forecast steps (of ``dt_s``) a candidate velocity is checked for.
        margin_m: required gap to every forecast position, metres.
    """

    def __init__(self, cfg: CrowdNavConfig, lookahead_steps: int = 6, margin_m: float = 0.2) -> None:
        self.cfg = cfg
        self.lookahead = min(lookahead_steps, cfg.horizon_steps)
        self.clear_m = cfg.robot_radius_m + cfg.pedestrian_radius_m + margin_m
        angles = np.deg2rad([0, 20, -20, 40, -40, 60, -60, 90, -90])
        speeds = np.array([1.0, 0.75, 0.5, 0.25])
        self._angles = np.repeat(angles, len(speeds))
        self._speeds = np.tile(speeds, len(angles))
        self._steps = cfg.dt_s * np.arange(1, self.lookahead + 1)

    def futures(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """``(m, L, 2)`` future positions of the observed pedestrians relative to the robot (m)."""
        cfg = self.cfg
        o = structured(obs, cfg.num_pedestrians, cfg.horizon_steps)
        mask = o["mask"].astype(bool)
        peds = o["pedestrians"][mask].astype(np.float64)
        if "forecasts" in o:
            return o["forecasts"][mask][:, : self.lookahead].astype(np.float64)
        ped_vel = peds[:, 2:4] + o["robot"][2:4].astype(np.float64)
        return peds[:, None, :2] + ped_vel[:, None, :] * self._steps[None, :, None]

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        cfg = self.cfg
        offset = np.asarray(obs["robot"][:2], dtype=np.float64)
        dist = float(np.hypot(offset[0], offset[1]))
        if dist < 1e-9:
            return np.zeros(2, dtype=np.float32)
        goal_dir = math.atan2(offset[1], offset[0])
        cap = min(cfg.robot_pref_speed_mps, dist / cfg.dt_s)
        theta = goal_dir + self._angles
        speed = self._speeds * cap
        vel = np.stack([speed * np.cos(theta), speed * np.sin(theta)], axis=1)  # (C, 2)
        fut = self.futures(obs)
        if len(fut) == 0:
            return velocity_to_action(vel[0], obs["robot"], cfg)
        path = vel[:, None, :] * self._steps[None, :, None]  # (C, L, 2)
        gap = np.linalg.norm(path[:, None] - fut[None], axis=-1).min(axis=(1, 2))  # (C,)
        progress = speed * np.cos(self._angles)
        stop_gap = float(np.linalg.norm(fut, axis=-1).min())
        ok = gap >= self.clear_m
        if ok.any():
            best = int(np.argmax(np.where(ok, progress, -np.inf)))
            if stop_gap >= self.clear_m and progress[best] <= 0:
                return np.zeros(2, dtype=np.float32)
            return velocity_to_action(vel[best], obs["robot"], cfg)
        if stop_gap >= self.clear_m:
            return np.zeros(2, dtype=np.float32)
        return velocity_to_action(vel[int(np.argmax(gap))], obs["robot"], cfg)
