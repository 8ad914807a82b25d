"""Reward components and episode metrics — identical in every forecast arm.

Nothing here sees the arm's forecasts: the optional future-intrusion term uses the replay's true future.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from envs.config import CrowdNavConfig

#: Names of the reward components, in the order they are summed.
REWARD_COMPONENTS: tuple[str, ...] = ("success", "collision", "discomfort", "progress", "intrusion", "time")


def reward_components(
    cfg: CrowdNavConfig,
    reached_goal: bool,
    collided: bool,
    min_gap_m: float,
    dist_before_m: float,
    dist_after_m: float,
    intruding: bool,
) -> dict[str, float]:
    """The named reward components of one step; the reward is their sum (in this order).

    Args:
        cfg: the configuration (weights).
        reached_goal: the robot is within the goal tolerance at the end of the step.
        collided: a robot-pedestrian contact began or lasted during the step.
        min_gap_m: smallest surface gap to any pedestrian during the step, metres (inf if none).
        dist_before_m: distance to the goal before the step, metres.
        dist_after_m: distance to the goal after the step, metres.
        intruding: the robot stands on a pedestrian's true future path within the horizon.

    Returns:
        ``success`` (+success_reward if the goal was reached without contact), ``collision``
        (collision_penalty on a step with contact), ``discomfort`` ((gap - discomfort_dist_m) x
        discomfort_scale x dt_s when the gap is below discomfort_dist_m and there was no contact),
        ``progress`` (progress_weight x (gamma x phi(s') - phi(s)), phi = -distance to goal) and
        ``intrusion`` (intrusion_penalty when intruding) and ``time`` (time_penalty, every step).
    """
    success = cfg.success_reward if (reached_goal and not collided) else 0.0
    collision = cfg.collision_penalty if collided else 0.0
    if not collided and min_gap_m < cfg.discomfort_dist_m:
        discomfort = (max(min_gap_m, 0.0) - cfg.discomfort_dist_m) * cfg.discomfort_scale * cfg.dt_s
    else:
        discomfort = 0.0
    progress = cfg.progress_weight * (cfg.progress_gamma * -dist_after_m + dist_before_m)
    intrusion = cfg.intrusion_penalty if intruding else 0.0
    return {
        "success": float(success),
        "collision": float(collision),
        "discomfort": float(discomfort),
        "progress": float(progress),
        "intrusion": float(intrusion),
        "time": float(cfg.time_penalty),
    }


def total_reward(components: dict[str, float]) -> float:
    """The reward: the plain sum of the components in :data:`REWARD_COMPONENTS` order."""
    return float(sum(components[k] for k in REWARD_COMPONENTS))


def time_to_collision(rel_position: np.ndarray, rel_velocity: np.ndarray, radius_sum_m: float) -> np.ndarray:
    """Constant-velocity time to collision of pairs of disks, seconds.

    Two disks whose centres are ``p`` apart (``rel_position``, the other's centre minus one's) and move apart at
    ``v`` (``rel_velocity``, the other's velocity minus one's) touch when ``|p + v t| = radius_sum_m``. The time is
    the smallest ``t >= 0`` solving it: ``0`` for disks already touching or overlapping, ``inf`` for disks that
    never touch (moving apart, at rest relative to each other, or passing wide). Head-on at distance ``d`` and
    closing speed ``s``: ``(d - radius_sum_m) / s``.

    Args:
        rel_position: ``(N, 2)`` metres.
        rel_velocity: ``(N, 2)`` m/s.
        radius_sum_m: sum of the two radii, metres.

    Returns:
        ``(N,)`` seconds (``inf`` where the disks never touch).
    """
    p = np.asarray(rel_position, dtype=np.float64).reshape(-1, 2)
    v = np.asarray(rel_velocity, dtype=np.float64).reshape(-1, 2)
    a = np.einsum("ij,ij->i", v, v)
    b = np.einsum("ij,ij->i", p, v)  # < 0: closing
    c = np.einsum("ij,ij->i", p, p) - radius_sum_m**2
    disc = b * b - a * c
    hit = (b < 0) & (a > 0) & (disc >= 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0.0))) / np.where(a > 0, a, 1.0), np.inf)
    return np.where(c <= 0, 0.0, t)


def min_time_to_collision(
    robot_position: np.ndarray,
    robot_velocity: np.ndarray,
    positions: np.ndarray,
    velocities: np.ndarray,
    present: np.ndarray,
    radius_sum_m: float,
) -> float:
    """The smallest constant-velocity :func:`time_to_collision` between the robot and the present pedestrians,
    seconds (``inf`` when none is on a collision course).

    Args:
        robot_position: ``(2,)`` metres; robot_velocity: ``(2,)`` m/s.
        positions: ``(N, 2)`` pedestrian positions, metres; velocities: ``(N, 2)`` m/s.
        present: ``(N,)`` bool: which rows hold a pedestrian.
        radius_sum_m: robot radius plus pedestrian radius, metres.
    """
    mask = np.asarray(present, dtype=bool)
    if not mask.any():
        return math.inf
    rel_p = np.asarray(positions, dtype=np.float64)[mask] - np.asarray(robot_position, dtype=np.float64)
    rel_v = np.asarray(velocities, dtype=np.float64)[mask] - np.asarray(robot_velocity, dtype=np.float64)
    return float(time_to_collision(rel_p, rel_v, radius_sum_m).min())


#: A readable name of every key of the episode metrics (:meth:`EpisodeMetrics.summary`), with its unit. Outputs
#: for people print the key itself beside its label (:func:`metric_label`), so a line of the demo or of an
#: evaluation's table names the JSON key it shows.
METRIC_LABELS: Final[dict[str, str]] = {
    "outcome": "outcome",
    "collision_fault": "collision: who moved into whom",
    "collisions": "collisions (contacts begun)",
    "navigation_time_s": "navigation time, s",
    "path_length_m": "path length, m",
    "path_ratio": "path length / straight-line distance (goal tolerance not subtracted)",
    "path_ratio_required": "path length / distance required (straight line minus goal tolerance)",
    "spl": "SPL: success x distance required / max(path length, distance required)",
    "min_gap_m": "closest surface gap to a pedestrian, m (negative: overlap in a collision)",
    "min_clearance_m": "closest surface distance to a pedestrian, m (0 at contact)",
    "min_ttc_s": "minimum time to collision at constant velocities, s",
    "discomfort_frequency": "share of steps closer than the discomfort distance",
    "intrusion_ratio": "share of steps on a pedestrian's future path",
    "mean_speed_mps": "mean speed, m/s",
    "mean_accel_mps2": "mean acceleration, m/s^2",
    "mean_jerk_mps3": "mean jerk, m/s^3",
    "forecast_ade_m": "forecast error, average over the horizon (ADE), m",
    "forecast_fde_m": "forecast error at the horizon's end (FDE), m",
    "mean_visible_pedestrians": "pedestrians observed per step (mean)",
    "crowd_density": "crowd density: pedestrians near the straight path (mean)",
    "pedestrians_near_path": "pedestrians near the straight path (distinct)",
    "popin_events": "tracks that began on the robot (kept as contact-less ghosts)",
    "steps": "steps",
    "return": "return (sum of rewards)",
    "r": "return (sum of rewards)",
    "l": "length, steps",
}


def metric_label(key: str) -> str:
    """``key`` with its readable label (:data:`METRIC_LABELS`), the one way outputs for people name a metric:
    ``"min_gap_m (closest surface gap ...)"``; an unknown key alone."""
    label = METRIC_LABELS.get(key)
    return key if label is None or label == key else f"{key} ({label})"


@dataclass
class EpisodeMetrics:
    """Accumulates an episode's metrics step by step; :meth:`summary` gives ``info["episode_metrics"]``.

    Args:
        start: ``(2,)`` robot start, metres.
        goal: ``(2,)`` goal, metres.
        dt_s: control step, seconds.
        discomfort_dist_m: gap below which a step counts as uncomfortable, metres.
        crowd_density: the episode's policy-independent crowd density (see :func:`envs.episodes.crowd_near_path`).
        pedestrians_near_path: pedestrians within sensor range of the start-goal segment during the episode.
        goal_tolerance_m: the goal counts as reached within this distance, metres; the distance an episode
            requires is the straight line minus it (``path_ratio_required``, ``spl``).
    """

    start: np.ndarray
    goal: np.ndarray
    dt_s: float
    discomfort_dist_m: float
    crowd_density: float = 0.0
    pedestrians_near_path: int = 0
    goal_tolerance_m: float = 0.0
    visible_sum: int = 0
    steps: int = 0
    episode_return: float = 0.0
    path_length_m: float = 0.0
    min_gap_m: float = math.inf
    discomfort_steps: int = 0
    intrusion_steps: int = 0
    collisions: int = 0
    collision_fault: str | None = None
    popin_events: int = 0
    ade_sum: float = 0.0
    ade_count: int = 0
    fde_sum: float = 0.0
    fde_count: int = 0
    jerk_sum: float = 0.0
    jerk_count: int = 0
    accel_sum: float = 0.0
    min_ttc_s: float = math.inf
    _velocities: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def of_episode(cls, episode: Any, dt_s: float, discomfort_dist_m: float, goal_tolerance_m: float) -> EpisodeMetrics:
        """Fresh metrics of an :class:`envs.episodes.Episode` (its start, goal and crowd density)."""
        return cls(
            episode.start.copy(),
            episode.goal.copy(),
            dt_s,
            discomfort_dist_m,
            crowd_density=episode.crowd_density,
            pedestrians_near_path=episode.pedestrians_near_path,
            goal_tolerance_m=goal_tolerance_m,
        )

    def update(
        self,
        reward: float,
        displacement_m: float,
        velocity: np.ndarray,
        min_gap_m: float,
        intruding: bool,
        new_contacts: int,
        fault: str | None,
        num_visible: int = 0,
        ttc_s: float = math.inf,
    ) -> None:
        """Record one step (``velocity``: ``(2,)`` m/s average over the step; ``num_visible``: pedestrians in the
        observation at its end; ``ttc_s``: the smallest constant-velocity time to collision with a pedestrian at
        its end, :func:`min_time_to_collision`, ``inf`` when none is on a collision course)."""
        self.steps += 1
        self.min_ttc_s = min(self.min_ttc_s, ttc_s)
        self.visible_sum += num_visible
        self.episode_return += reward
        self.path_length_m += displacement_m
        self.min_gap_m = min(self.min_gap_m, min_gap_m)
        self.discomfort_steps += int(min_gap_m < self.discomfort_dist_m)
        self.intrusion_steps += int(intruding)
        self.collisions += new_contacts
        if fault is not None and self.collision_fault is None:
            self.collision_fault = fault
        v = self._velocities
        v.append(np.asarray(velocity, dtype=np.float64))
        if len(v) > 3:
            del v[0]
        # velocities before the first step are 0 (the robot starts at rest)
        vs = [np.zeros(2)] * max(0, 3 - len(v)) + v
        accel = (vs[2] - vs[1]) / self.dt_s
        self.accel_sum += float(np.hypot(accel[0], accel[1]))
        if self.steps >= 2:
            jerk = (vs[2] - 2 * vs[1] + vs[0]) / self.dt_s**2
            self.jerk_sum += float(np.hypot(jerk[0], jerk[1]))
            self.jerk_count += 1

    def add_forecast_errors(self, errors: np.ndarray, valid: np.ndarray) -> None:
        """Displacement errors ``(m, H)`` metres of the arm's forecasts against the truth (``valid`` ``(m, H)``)."""
        if errors.size == 0:
            return
        self.ade_sum += float(errors[valid].sum())
        self.ade_count += int(valid.sum())
        last = valid[:, -1]
        self.fde_sum += float(errors[last, -1].sum())
        self.fde_count += int(last.sum())

    def summary(self, outcome: str, time_s: float, has_forecasts: bool) -> dict[str, Any]:
        """The episode's metrics (JSON-ready; ``None`` where not defined).

        Keys: ``outcome`` (success, collision, timeout), ``collision_fault`` (robot, pedestrian or
        None), ``collisions`` (contacts begun), ``navigation_time_s``, ``path_length_m``,
        ``path_ratio`` (path length / straight line; below 1 for a trip that stops within the goal tolerance),
        ``path_ratio_required`` (path length / the distance required: straight line minus ``goal_tolerance_m``; at
        least 1 for a success), ``spl`` (success weighted by path length, Anderson et al. 2018: the distance required
        / max(path length, distance required) for a success, 0 otherwise), ``min_gap_m`` (smallest surface gap to
        a pedestrian, negative while overlapping in a collision), ``min_clearance_m`` (the same, 0 at contact),
        ``min_ttc_s`` (smallest constant-velocity time to collision with a present pedestrian at the end of a step,
        :func:`min_time_to_collision`; 0 at contact, None when no pedestrian was ever on a collision course),
        ``discomfort_frequency`` (share of steps with a gap below discomfort_dist_m), ``intrusion_ratio`` (share of
        steps on a pedestrian's true future path), ``mean_speed_mps`` (path length / time), ``mean_accel_mps2``
        (mean magnitude of the change of velocity per step / dt, from rest), ``mean_jerk_mps3``, ``forecast_ade_m``,
        ``forecast_fde_m`` (the arm's forecasts of the observed pedestrians against the replay's
        truth), ``mean_visible_pedestrians`` (pedestrians in the observation, mean over steps),
        ``crowd_density`` and ``pedestrians_near_path`` (as in the reset info), ``popin_events`` (pedestrians
        whose track began on the robot and were kept as contact-less ghosts, see :mod:`envs.popin`), ``steps``,
        and ``r``/``l``
        (return and length; kept so the metrics are complete without a monitoring wrapper).
        """
        straight = float(np.linalg.norm(self.goal - self.start))
        required = straight - self.goal_tolerance_m
        n = max(self.steps, 1)
        success = outcome == "success"
        return {
            "outcome": outcome,
            "collision_fault": self.collision_fault,
            "collisions": self.collisions,
            "navigation_time_s": round(time_s, 9),
            "path_length_m": self.path_length_m,
            "path_ratio": self.path_length_m / straight if straight > 0 else None,
            "path_ratio_required": self.path_length_m / required if required > 0 else None,
            "spl": (required / max(self.path_length_m, required) if success else 0.0) if required > 0 else None,
            "min_gap_m": None if math.isinf(self.min_gap_m) else self.min_gap_m,
            "min_clearance_m": None if math.isinf(self.min_gap_m) else max(self.min_gap_m, 0.0),
            "min_ttc_s": None if math.isinf(self.min_ttc_s) else self.min_ttc_s,
            "discomfort_frequency": self.discomfort_steps / n,
            "intrusion_ratio": self.intrusion_steps / n,
            "mean_speed_mps": self.path_length_m / (self.steps * self.dt_s) if self.steps else 0.0,
            "mean_accel_mps2": self.accel_sum / self.steps if self.steps else 0.0,
            "mean_jerk_mps3": self.jerk_sum / self.jerk_count if self.jerk_count else 0.0,
            "forecast_ade_m": (self.ade_sum / self.ade_count) if (has_forecasts and self.ade_count) else None,
            "forecast_fde_m": (self.fde_sum / self.fde_count) if (has_forecasts and self.fde_count) else None,
            "mean_visible_pedestrians": self.visible_sum / n,
            "crowd_density": self.crowd_density,
            "pedestrians_near_path": self.pedestrians_near_path,
            "popin_events": self.popin_events,
            "steps": self.steps,
            "r": self.episode_return,
            "l": self.steps,
        }
