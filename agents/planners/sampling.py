"""The sampling planner: one velocity, chosen among candidates, checked against the observed pedestrians' futures."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np

from agents.planners.base import _fractions_and_headings, _goal_velocity, _Planner, region_radii, velocities_to_actions
from envs.config import CrowdNavConfig
from envs.observation import structured

#: Default candidate headings relative to the goal direction, degrees (9 headings).
DEFAULT_HEADINGS_DEG: Final[tuple[float, ...]] = (0.0, 20.0, -20.0, 40.0, -40.0, 60.0, -60.0, 90.0, -90.0)
#: Default candidate speeds as fractions of the speed cap (4 speeds; with standing still: 9 x 4 + 1 = 37 candidates).
DEFAULT_SPEED_FRACTIONS: Final[tuple[float, ...]] = (1.0, 0.75, 0.5, 0.25)
#: Dense candidate headings (``candidates="dense"``): 16 around the full circle, backing away included, degrees.
DENSE_HEADINGS_DEG: Final[tuple[float, ...]] = (0.0, *(s * 22.5 * k for k in range(1, 8) for s in (1, -1)), 180.0)
#: Dense candidate speeds (6; with standing still: 16 x 6 + 1 = 97 candidates).
DENSE_SPEED_FRACTIONS: Final[tuple[float, ...]] = (1.0, 0.8, 0.6, 0.4, 0.2, 0.1)
#: Named candidate sets of the sampling planner: ``(headings_deg, speed_fractions)``.
CANDIDATE_SETS: Final[dict[str, tuple[tuple[float, ...], tuple[float, ...]]]] = {
    "default": (DEFAULT_HEADINGS_DEG, DEFAULT_SPEED_FRACTIONS),
    "dense": (DENSE_HEADINGS_DEG, DENSE_SPEED_FRACTIONS),
}


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
        headings_deg: candidate headings relative to the goal direction, degrees (default: the ``candidates`` set's).
        speed_fractions: candidate speeds as fractions of the speed cap, in (0, 1] (default: the set's).
        candidates: a named set of :data:`CANDIDATE_SETS`: ``default`` (9 headings within ±90° x 4 speeds + standing
            = 37) or ``dense`` (16 headings around the full circle, backing away included, x 6 speeds + standing = 97).
        uncertainty: require clearance of each forecast step's uncertainty region instead of its point: the
            gap is measured from the edge of the disc of radius ``forecast_uncertainty`` (the observation key of
            ``forecast_uncertainty=True``, a calibrated region) around the forecast position. Needs that key.
    """

    def __init__(
        self,
        env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
        lookahead_steps: int = 6,
        margin_m: float = 0.2,
        headings_deg: Sequence[float] | None = None,
        speed_fractions: Sequence[float] | None = None,
        candidates: str = "default",
        uncertainty: bool = False,
    ) -> None:
        super().__init__(env_config)
        self.uncertainty = bool(uncertainty)
        cfg = self.cfg
        if lookahead_steps < 1:
            raise ValueError(f"lookahead_steps must be >= 1, got {lookahead_steps!r}")
        if candidates not in CANDIDATE_SETS:
            raise ValueError(f"unknown candidates {candidates!r}; valid: {', '.join(CANDIDATE_SETS)}")
        set_headings, set_speeds = CANDIDATE_SETS[candidates]
        angles, speeds = _fractions_and_headings(
            set_headings if headings_deg is None else headings_deg,
            set_speeds if speed_fractions is None else speed_fractions,
        )
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
        return region_radii(obs, self.cfg, self.lookahead, self.uncertainty)

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
