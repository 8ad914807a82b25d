"""Non-learned policies with Stable-Baselines3's ``predict`` interface.

- :class:`StraightToGoal`: straight to the goal at the preferred speed, slowing down to stop on it.
- :class:`SamplingPlanner`: scores candidate velocities (headings around the goal direction times
  speeds, plus standing still) against the future positions of the observed pedestrians — the
  forecasts the observation carries, or constant-velocity extrapolations of their observed
  velocities when it has none (the ``none`` arm) — and takes the fastest progress that stays clear
  over a few steps of that one velocity. ``candidates="dense"`` (16 headings around the full circle,
  backing away included, x 6 speeds) widens its choice.
- :class:`SearchPlanner`: a layered search over *sequences* of velocities several seconds ahead against
  the same futures, with candidates that back away, replanned every step (the fastest arrival, or the
  closest approach to the goal that stays clear).
- :class:`agents.privileged.PrivilegedPlanner` (``make_planner("privileged")``): PRIVILEGED, reads the
  replay's true future of every pedestrian; the ceiling of what is attainable, never a policy.

All but the privileged one read only the observation. Each accepts a single observation dict or a
batched one (a leading dimension on every key) and returns ``(actions, None)`` like an SB3 model, so
evaluation (and DAgger, which uses a planner as its teacher) treats planners and learned policies
alike; the scoring and the search are vectorised over the batch, and a batched ``predict`` equals one
``predict`` per observation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np

from envs.config import CrowdNavConfig, config_from
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
    with ``forecast_uncertainty=True`` (a calibrated disc, :mod:`envs.uncertainty`) --; without it, 0 (points).

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


# ---------------------------------------------------------------------------- search over velocity sequences


def motion_candidates(
    states: np.ndarray,
    goal: np.ndarray,
    base_dir: np.ndarray,
    speed_mps: float,
    dt_s: float,
    headings_rad: np.ndarray,
    fractions: np.ndarray,
) -> np.ndarray:
    """Candidate velocities of the search planners from each state.

    Every heading of ``headings_rad`` (relative to ``base_dir``) at every speed fraction of ``speed_mps``
    (heading-major), then straight at the goal at every fraction of the cap ``min(speed_mps, distance / dt_s)``
    (the first arrives exactly when the goal is within a step), then standing still:
    ``A = len(headings) * len(fractions) + len(fractions) + 1`` velocities.

    Args:
        states: ``(..., 2)`` positions, metres.
        goal: ``(..., 2)`` (broadcast against ``states``) goal, same frame.
        base_dir: ``(...)`` (broadcast) direction the headings are measured from, radians.
        speed_mps: the speed cap, m/s.
        dt_s: control step, seconds.
        headings_rad: ``(Hd,)`` radians; fractions: ``(F,)`` in (0, 1].

    Returns:
        ``(..., A, 2)`` velocities, m/s.
    """
    angles = np.asarray(base_dir, dtype=np.float64)[..., None] + headings_rad  # (..., Hd)
    lead = np.broadcast_shapes(states.shape[:-1], goal.shape[:-1], angles.shape[:-1])
    fixed = speed_mps * fractions[None, :, None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)[..., None, :]
    fixed = np.broadcast_to(fixed, (*lead, len(headings_rad), len(fractions), 2)).reshape(*lead, -1, 2)
    offset = goal - states
    dist = np.hypot(offset[..., 0], offset[..., 1])
    unit = offset / np.where(dist > 1e-9, dist, 1.0)[..., None]
    cap = np.minimum(speed_mps, dist / dt_s)
    towards = np.broadcast_to((cap[..., None] * fractions)[..., None] * unit[..., None, :], (*lead, len(fractions), 2))
    stand = np.zeros((*lead, 1, 2))
    return np.concatenate([fixed, towards, stand], axis=-2)


def lattice_select(
    group: np.ndarray, points: np.ndarray, prefer: np.ndarray, rank: np.ndarray, cell_m: float, keep: int | None
) -> np.ndarray:
    """The entries a layered search keeps: one per (group, cell of a ``cell_m`` lattice), the one with the smallest
    ``prefer`` level (ties: the first), then per group the ``keep`` entries with the smallest ``rank`` (all if None).

    Args:
        group: ``(E,)`` int >= 0 (the environment of each entry; groups never influence each other).
        points: ``(E, 2)`` metres.
        prefer: ``(E,)`` int levels in ``[0, 4096)``.
        rank: ``(E,)`` float.

    Returns:
        indices into the entries, sorted by group, then rank.
    """
    cells = np.floor(points / cell_m)
    if len(cells) and np.abs(cells).max() >= _CELL_OFFSET:
        raise ValueError(f"points up to {np.abs(points).max():.3g} m lie too far out for a {cell_m} m lattice")
    cells = cells.astype(np.int64) + _CELL_OFFSET
    level = np.clip(prefer, 0, _LEVELS - 1).astype(np.int64)
    key = ((group.astype(np.int64) * _CELL_SPAN + cells[:, 0]) * _CELL_SPAN + cells[:, 1]) * _LEVELS + level
    order = np.argsort(key, kind="stable")
    cell = key[order] // _LEVELS
    idx = order[np.r_[True, cell[1:] != cell[:-1]]]
    idx = idx[np.lexsort((rank[idx], group[idx]))]
    if keep is None or len(idx) == 0:
        return idx
    g = group[idx]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    within = np.arange(len(idx)) - np.repeat(starts, np.diff(np.r_[starts, len(idx)]))
    return idx[within < keep]


#: Lattice cells are packed with the group and the preference level into one int64 (groups below 2**9): cell
#: indices must lie within ±_CELL_OFFSET, levels in [0, _LEVELS).
_CELL_OFFSET: Final[int] = 2**20
_CELL_SPAN: Final[int] = 2**21
_LEVELS: Final[int] = 2**12


#: Observations searched at once by :class:`SearchPlanner` (memory grows with it; results do not depend on it).
_SEARCH_CHUNK: Final[int] = 16
#: Headings of the search planners, degrees from the goal direction: 16 around the full circle (backing away too).
SEARCH_HEADINGS_DEG: Final[tuple[float, ...]] = tuple(22.5 * k for k in range(16))
#: Speeds of the search planners, fractions of the preferred speed (and of the goal-directed cap).
SEARCH_SPEED_FRACTIONS: Final[tuple[float, ...]] = (1.0, 0.6, 0.3)


def _fractions_and_headings(headings_deg: Sequence[float], speed_fractions: Sequence[float]) -> tuple[np.ndarray, ...]:
    """Checked ``(headings (Hd,) radians, fractions (F,))``; ``ValueError`` naming the bad option."""
    angles = np.deg2rad(np.asarray(headings_deg, dtype=np.float64).reshape(-1))
    speeds = np.asarray(speed_fractions, dtype=np.float64).reshape(-1)
    if not len(angles) or not len(speeds):
        raise ValueError("headings_deg and speed_fractions must not be empty")
    if not np.all((speeds > 0) & (speeds <= 1)):
        raise ValueError(f"speed_fractions must lie in (0, 1], got {speeds.tolist()!r}")
    return angles, speeds


class SearchPlanner(_Planner):
    """Plans a sequence of velocities over several seconds against the observed pedestrians' futures; replans every
    step and takes the first velocity of the best plan.

    A layered search in time: from the robot, each layer (one control step, ``dt_s``) expands every state by
    :func:`motion_candidates` (16 headings around the full circle x 3 speeds, 3 goal-directed speeds, standing:
    52 velocities), drops children that come closer than the sum of radii plus ``margin_m`` (growing by
    ``margin_growth_mps`` per second of look-ahead) to an observed pedestrian at any time of the step (closest
    approach of the two straight motions, exact), keeps one child per ``cell_m`` lattice cell (the one with the
    largest clearance so far) and the ``max_states`` nearest the goal. The first layer with a child on the goal
    ends the search (the fastest arrival; the clearest one among them); otherwise, after ``lookahead_steps``
    layers, or at the last layer any state survived, the best state minimises the distance to the goal plus
    ``clearance_weight`` x the shortfall of its clearance below ``clearance_pref_m``. When no first velocity is
    clear, the one with the largest gap over the first step is taken.

    The futures are the observation's forecasts (``(K, H, 2)``) or, without them (the ``none`` arm),
    constant-velocity extrapolations of the observed velocities; only the observation is used. With
    ``uncertainty=True`` a pedestrian is a region, not a point: during each step its disk grows by the larger
    radius of the step's two ends of ``forecast_uncertainty`` (0 at the present, observed position), so every gap,
    clearance and the escape are measured from the edge of the region (as :class:`SamplingPlanner` does). Motions are
    holonomic; with unicycle kinematics the first velocity is turned into an action by
    :func:`velocities_to_actions`. Every environment of a batch is searched at once (numpy over ``(B, M, A, K)``)
    and independently: a batched ``predict`` equals one ``predict`` per observation.

    Args:
        env_config: the environment's configuration.
        lookahead_steps: layers searched, control steps (at most H; default 10 = 4 s at 0.4 s).
        margin_m: required gap beyond touching at the first step, metres.
        margin_growth_mps: added to the margin per second of look-ahead, metres per second.
        margin_per_m: added to the margin of a pedestrian per metre its future has moved it from where it is now
            (forecast errors grow with the distance forecast), metres per metre.
        headings_deg: headings relative to the goal direction, degrees.
        speed_fractions: speeds as fractions of the preferred speed, in (0, 1].
        cell_m: lattice of the de-duplication, metres.
        max_states: states kept per layer and environment.
        clearance_pref_m: gaps below this count against a plan that does not reach the goal, metres.
        clearance_weight: metres of distance a metre of clearance shortfall is worth.
        uncertainty: require clearance of each forecast step's uncertainty region instead of its point (the
            observation key ``forecast_uncertainty`` of ``forecast_uncertainty=True``; see :func:`region_radii`).
            Needs that key.
    """

    def __init__(
        self,
        env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
        lookahead_steps: int = 10,
        margin_m: float = 0.05,
        margin_growth_mps: float = 0.05,
        margin_per_m: float = 0.0,
        headings_deg: Sequence[float] = SEARCH_HEADINGS_DEG,
        speed_fractions: Sequence[float] = SEARCH_SPEED_FRACTIONS,
        cell_m: float = 0.15,
        max_states: int = 150,
        clearance_pref_m: float = 0.3,
        clearance_weight: float = 1.0,
        uncertainty: bool = False,
    ) -> None:
        super().__init__(env_config)
        cfg = self.cfg
        self.uncertainty = bool(uncertainty)
        if lookahead_steps < 1:
            raise ValueError(f"lookahead_steps must be >= 1, got {lookahead_steps!r}")
        for name, value in (
            ("margin_m", margin_m),
            ("margin_growth_mps", margin_growth_mps),
            ("margin_per_m", margin_per_m),
        ):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell_m must be a finite number > 0, got {cell_m!r}")
        if max_states < 1:
            raise ValueError(f"max_states must be >= 1, got {max_states!r}")
        self.headings, self.fractions = _fractions_and_headings(headings_deg, speed_fractions)
        self.lookahead = min(int(lookahead_steps), cfg.horizon_steps)
        self.r_sum = cfg.robot_radius_m + cfg.pedestrian_radius_m
        self.margins = float(margin_m) + float(margin_growth_mps) * cfg.dt_s * np.arange(self.lookahead)  # (L,)
        self.margin_per_m = float(margin_per_m)
        self.cell_m = float(cell_m)
        self.max_states = int(max_states)
        self.clearance_pref_m = float(clearance_pref_m)
        self.clearance_weight = float(clearance_weight)
        #: centre distance beyond the robot's step from which a pedestrian cannot matter in a step, metres
        self.far_m = self.r_sum + max(float(self.margins.max()), self.clearance_pref_m) + 1e-6
        self._steps = cfg.dt_s * np.arange(self.lookahead + 1)  # (L + 1,) seconds

    @property
    def num_candidates(self) -> int:
        """Velocities tried from every state."""
        return len(self.headings) * len(self.fractions) + len(self.fractions) + 1

    def futures(self, obs: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Positions of the observation rows relative to the robot now and over the look-ahead.

        Returns:
            ``(positions (B, K, L + 1, 2) metres at t + h dt_s, h = 0..L; mask (B, K) bool)``.
        """
        cfg = self.cfg
        o = structured(dict(obs), cfg.num_pedestrians, cfg.horizon_steps)
        mask = o["mask"].astype(bool)
        peds = o["pedestrians"].astype(np.float64)
        now = peds[..., :2]
        if "forecasts" in o:
            ahead = o["forecasts"][:, :, : self.lookahead].astype(np.float64)
            return np.concatenate([now[:, :, None], ahead], axis=2), mask
        ped_vel = peds[..., 2:4] + o["robot"][:, None, 2:4].astype(np.float64)  # (B, K, 2) world velocity
        return now[:, :, None, :] + ped_vel[:, :, None, :] * self._steps[None, None, :, None], mask

    def step_inflation(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """``(B, K, L)`` metres each pedestrian's disk grows by during look-ahead step ``h`` (from ``t + h dt_s`` to
        ``t + (h + 1) dt_s``) for its uncertainty region: the larger radius of the step's two ends (the region at
        the present, observed position is 0), with ``uncertainty=True``; 0 without."""
        ahead = region_radii(obs, self.cfg, self.lookahead, self.uncertainty)  # (B, K, L) at t + (h + 1) dt_s
        before = np.concatenate([np.zeros_like(ahead[:, :, :1]), ahead[:, :, :-1]], axis=2)
        return np.maximum(before, ahead)

    def _gaps(
        self,
        x: np.ndarray,
        valid: np.ndarray,
        move: np.ndarray,
        q0: np.ndarray,
        q1: np.ndarray,
        mask: np.ndarray,
        inflate: np.ndarray | None = None,
    ) -> np.ndarray:
        """Smallest surface gap ``(B, M, A)`` during a step, metres: robots from ``x`` ``(B, M, 2)`` (rows in ``valid``)
        moving by ``move`` ``(B, M, A, 2)``, pedestrians from ``q0`` to ``q1`` ``(B, K, 2)`` (rows in ``mask``), both
        straight and uniform (the exact closest approach), each pedestrian's disk grown by ``inflate`` ``(B, K)``
        metres (default 0). Pairs of a state and a pedestrian farther apart than :attr:`far_m` plus the growth and
        the robot's step are not computed: their gap is ``inf`` (it is at least ``far_m`` minus the sum of radii)."""
        grow = np.zeros(mask.shape) if inflate is None else inflate
        seg = q1 - q0  # (B, K, 2)
        w = x[:, :, None, :] - q0[:, None, :, :]  # (B, M, K, 2)
        seg2 = seg[..., 0] * seg[..., 0] + seg[..., 1] * seg[..., 1]
        u = (w[..., 0] * seg[:, None, :, 0] + w[..., 1] * seg[:, None, :, 1]) / np.where(seg2 > 1e-12, seg2, 1.0)[
            :, None
        ]
        u = np.clip(u, 0.0, 1.0)
        near = np.hypot(w[..., 0] - u * seg[:, None, :, 0], w[..., 1] - u * seg[:, None, :, 1])  # state to path
        reach = self.far_m + np.hypot(move[..., 0], move[..., 1]).max(axis=2)  # (B, M)
        bi, mi, ki = np.nonzero((near < reach[..., None] + grow[:, None, :]) & valid[..., None] & mask[:, None, :])
        gap = np.full(move.shape[:3], np.inf)
        if len(bi) == 0:
            return gap
        d0 = w[bi, mi, ki]  # (n, 2)
        dd = move[bi, mi] - seg[bi, ki][:, None, :]  # (n, A, 2)
        num = d0[:, None, 0] * dd[..., 0] + d0[:, None, 1] * dd[..., 1]
        den = dd[..., 0] * dd[..., 0] + dd[..., 1] * dd[..., 1]
        t = np.clip(-num / np.where(den > 1e-12, den, 1.0), 0.0, 1.0)
        dist = np.hypot(d0[:, None, 0] + t * dd[..., 0], d0[:, None, 1] + t * dd[..., 1])  # (n, A)
        dist -= grow[bi, ki][:, None]
        starts = np.flatnonzero(np.r_[True, (bi[1:] != bi[:-1]) | (mi[1:] != mi[:-1])])
        gap[bi[starts], mi[starts]] = np.minimum.reduceat(dist, starts, axis=0) - self.r_sum
        return gap

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        cfg = self.cfg
        robot = obs["robot"]
        b_all = len(robot)
        goal, dist, cap = _goal_velocity(robot, cfg)  # goal relative to the robot
        fut, mask = self.futures(obs)
        grow = self.step_inflation(obs)
        scale = np.divide(cap, dist, out=np.zeros_like(dist), where=dist >= 1e-9)
        chosen = goal * scale[:, None]  # no pedestrian observed: straight at the goal
        todo = np.flatnonzero(mask.any(axis=1) & (dist >= 1e-9))
        for lo in range(0, len(todo), _SEARCH_CHUNK):  # bounded memory for large batches (DAgger labels thousands)
            rows = todo[lo : lo + _SEARCH_CHUNK]
            chosen[rows] = self._search(goal[rows], fut[rows], mask[rows], grow[rows])
        return velocities_to_actions(chosen, robot.reshape(b_all, -1), cfg)

    def _search(self, goal: np.ndarray, fut: np.ndarray, mask: np.ndarray, grow: np.ndarray) -> np.ndarray:
        """First velocities ``(B, 2)`` of the best plans (goal ``(B, 2)`` and futures relative to the robot; ``grow``
        ``(B, K, L)``: :meth:`step_inflation`)."""
        cfg = self.cfg
        b = len(goal)
        dt, v, tol = cfg.dt_s, cfg.robot_pref_speed_mps, cfg.goal_tolerance_m - 1e-6
        base = np.arctan2(goal[:, 1], goal[:, 0])
        x = np.zeros((b, 1, 2))  # states of the layer (padded), relative to the robot
        valid = np.ones((b, 1), dtype=bool)
        first = np.zeros((b, 1, 2))  # the first velocity of each state's plan
        clear = np.full((b, 1), np.inf)  # its smallest gap so far
        settled = np.zeros(b, dtype=bool)
        rows = np.arange(b)
        result = np.zeros((b, 2))
        for h in range(self.lookahead):
            vel = motion_candidates(x, goal[:, None], base[:, None], v, dt, self.headings, self.fractions)
            move = vel * dt
            travelled = np.hypot(*(fut[:, :, h + 1] - fut[:, :, 0]).transpose(2, 0, 1))  # (B, K) metres
            inflate = self.margin_per_m * travelled + grow[:, :, h]
            gap = self._gaps(x, valid, move, fut[:, :, h], fut[:, :, h + 1], mask, inflate)
            if h == 0:  # the first velocity of every plan; the escape (largest gap) when none is clear
                first = vel[:, 0][:, None].copy()  # (B, 1, A, 2) -> per child below
                result = vel[rows, 0, np.argmax(gap[:, 0], axis=1)]
            # clearance so far, counted up to clearance_pref_m (beyond it, plans are equally clear)
            path_clear = np.minimum(np.minimum(clear[..., None], gap), self.clearance_pref_m)
            ok = valid[..., None] & (gap >= self.margins[h]) & ~settled[:, None, None]
            gb, gm, ga = np.nonzero(ok)  # the surviving children, environment-major
            if len(gb) == 0:
                break
            child = x[gb, gm] + move[gb, gm, ga]  # (C, 2)
            first_c = first[gb, gm, ga] if h == 0 else first[gb, gm]
            clear_c = path_clear[gb, gm, ga]
            to_goal = np.hypot(goal[gb, 0] - child[:, 0], goal[gb, 1] - child[:, 1])
            starts = np.flatnonzero(np.r_[True, gb[1:] != gb[:-1]])
            envs = gb[starts]
            arrived = to_goal <= tol
            if arrived.any():  # the fastest arrival wins, the clearest among them
                best = np.maximum.reduceat(np.where(arrived, clear_c, -np.inf), starts)
                won = envs[best > -np.inf]
                pick = np.flatnonzero(arrived & (clear_c == best[np.searchsorted(envs, gb)]))
                pick = pick[np.r_[True, gb[pick][1:] != gb[pick][:-1]]]  # the first of each environment
                result[gb[pick]] = first_c[pick]
                settled[won] = True
                alive = ~settled[gb]
                gb, child, first_c, clear_c, to_goal = (
                    gb[alive],
                    child[alive],
                    first_c[alive],
                    clear_c[alive],
                    to_goal[alive],
                )
                if len(gb) == 0:
                    break
                starts = np.flatnonzero(np.r_[True, gb[1:] != gb[:-1]])
                envs = gb[starts]
            # the best plan so far of every environment still searching (its deepest layer wins)
            score = to_goal + self.clearance_weight * (self.clearance_pref_m - clear_c)
            low = np.minimum.reduceat(score, starts)
            pick = np.flatnonzero(score == low[np.searchsorted(envs, gb)])
            pick = pick[np.r_[True, gb[pick][1:] != gb[pick][:-1]]]
            result[gb[pick]] = first_c[pick]
            # one child per cell: the clearest (to the centimetre), then the nearest the goal
            level = np.rint((self.clearance_pref_m - clear_c) * 100.0)
            keep = lattice_select(gb, child, level, to_goal, self.cell_m, self.max_states)
            gb = gb[keep]
            counts = np.bincount(gb, minlength=b)
            slot = np.arange(len(gb)) - np.repeat(np.cumsum(counts) - counts, counts)
            m = int(counts.max())
            x, first = np.zeros((b, m, 2)), np.zeros((b, m, 2))
            valid, clear = np.zeros((b, m), dtype=bool), np.full((b, m), np.inf)
            x[gb, slot], first[gb, slot], clear[gb, slot] = child[keep], first_c[keep], clear_c[keep]
            valid[gb, slot] = True
        return result


#: Names accepted by :func:`make_planner` (``privileged`` reads the replay: see :mod:`agents.privileged`).
PLANNERS: Final[tuple[str, ...]] = ("straight", "planner", "search", "privileged")


def make_planner(name: str, env_config: CrowdNavConfig | Mapping[str, Any] | None = None, **kwargs: Any) -> Any:
    """A planner by name: ``"straight"`` (:class:`StraightToGoal`), ``"planner"`` (:class:`SamplingPlanner`),
    ``"search"`` (:class:`SearchPlanner`) or ``"privileged"`` (:class:`agents.privileged.PrivilegedPlanner`, which
    must be bound to its environments before it acts); ``kwargs`` are passed on."""
    if name == "straight":
        if kwargs:
            raise ValueError(f"the straight-to-goal policy takes no options, got {sorted(kwargs)}")
        return StraightToGoal(env_config)
    if name == "planner":
        return SamplingPlanner(env_config, **kwargs)
    if name == "search":
        return SearchPlanner(env_config, **kwargs)
    if name == "privileged":
        from agents.privileged import PrivilegedPlanner

        return PrivilegedPlanner(env_config, **kwargs)
    raise ValueError(f"unknown planner {name!r}; valid: {', '.join(PLANNERS)}")
