"""The search planner: a layered search over sequences of velocities several seconds ahead, replanned every step.

:func:`motion_candidates` and :func:`lattice_select` are shared with the privileged planner
(:mod:`agents.planners.privileged`), which searches the same way against the replay's true future.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np

from agents.planners.base import _fractions_and_headings, _goal_velocity, _Planner, region_radii, velocities_to_actions
from envs.config import CrowdNavConfig
from envs.observation import structured


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
#: With samples: observations searched at once times samples per pedestrian (at least one observation at a time).
_SAMPLED_ROWS_CHUNK: Final[int] = 64
#: Headings of the search planners, degrees from the goal direction: 16 around the full circle (backing away too).
SEARCH_HEADINGS_DEG: Final[tuple[float, ...]] = tuple(22.5 * k for k in range(16))
#: Speeds of the search planners, fractions of the preferred speed (and of the goal-directed cap).
SEARCH_SPEED_FRACTIONS: Final[tuple[float, ...]] = (1.0, 0.6, 0.3)


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
    clearance and the escape are measured from the edge of the region (as :class:`SamplingPlanner` does).

    With ``samples=True`` a pedestrian is its ``S`` sampled futures (the observation key ``forecast_samples``
    ``(K, S, H, 2)`` of ``forecast_samples=S``; each sample moves from the present, observed position), and the plan
    is chance-constrained: a step is admissible if it keeps the gap to at least ``sample_share`` of each
    pedestrian's samples (``k = ceil(sample_share S)`` of them), i.e. if the ``k``-th largest of the ``S`` gaps to a
    pedestrian is at least the margin; that ``k``-th largest gap is the pedestrian's gap everywhere a gap is used
    (clearance, the escape). With every sample on the point forecast it is the point gap, so the plans are the point
    planner's; ``sample_share=0`` keeps clear of nothing. Motions are
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
        samples: plan against the sampled futures of the observation key ``forecast_samples`` instead of the
            forecasts, chance-constrained (above). Needs that key; not with ``uncertainty``.
        sample_share: with ``samples``, the share of each pedestrian's samples a plan keeps clear of at every step,
            in [0, 1].
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
        samples: bool = False,
        sample_share: float = 0.9,
    ) -> None:
        super().__init__(env_config)
        cfg = self.cfg
        self.uncertainty = bool(uncertainty)
        self.samples = bool(samples)
        if self.samples and self.uncertainty:
            raise ValueError("samples and uncertainty are two ways to plan with a forecast's spread: choose one")
        if not (isinstance(sample_share, int | float) and 0.0 <= sample_share <= 1.0):
            raise ValueError(f"sample_share must be a number in [0, 1], got {sample_share!r}")
        self.sample_share = float(sample_share)
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
        """Positions of the observation rows relative to the robot now and over the look-ahead; with ``samples``,
        every sample of every row is a row (``K S`` of them, row-major: the samples of a pedestrian together).

        Returns:
            ``(positions (B, K, L + 1, 2) metres at t + h dt_s, h = 0..L; mask (B, K) bool)``.

        Raises:
            ValueError: ``samples`` without the observation key ``forecast_samples``.
        """
        cfg = self.cfg
        o = structured(dict(obs), cfg.num_pedestrians, cfg.horizon_steps)
        mask = o["mask"].astype(bool)
        peds = o["pedestrians"].astype(np.float64)
        now = peds[..., :2]
        if self.samples:
            if "forecast_samples" not in o:
                raise ValueError(
                    "the search planner's samples option needs the observation key 'forecast_samples' (make the "
                    f"environment with forecast_samples=S > 0 and a source with a distribution); got keys {sorted(obs)}"
                )
            ahead = o["forecast_samples"][:, :, :, : self.lookahead].astype(np.float64)  # (B, K, S, L, 2)
            b, k, s = ahead.shape[:3]
            start = np.broadcast_to(now[:, :, None, None, :], (b, k, s, 1, 2))
            rows = np.concatenate([start, ahead], axis=3).reshape(b, k * s, self.lookahead + 1, 2)
            return rows, np.repeat(mask, s, axis=1)
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
        group: int = 1,
    ) -> np.ndarray:
        """Smallest surface gap ``(B, M, A)`` during a step, metres: robots from ``x`` ``(B, M, 2)`` (rows in ``valid``)
        moving by ``move`` ``(B, M, A, 2)``, pedestrians from ``q0`` to ``q1`` ``(B, K, 2)`` (rows in ``mask``), both
        straight and uniform (the exact closest approach), each pedestrian's disk grown by ``inflate`` ``(B, K)``
        metres (default 0). Pairs of a state and a pedestrian farther apart than :attr:`far_m` plus the growth and
        the robot's step are not computed: their gap is ``inf`` (it is at least ``far_m`` minus the sum of radii).
        With ``group`` > 1 every ``group`` consecutive rows are one pedestrian's samples, and a pedestrian's gap is the
        ``k``-th largest of its rows' (``k = ceil(sample_share group)``; ``inf`` for ``k = 0``)."""
        keep = math.ceil(self.sample_share * group - 1e-9) if group > 1 else 1
        if keep == 0:
            return np.full(move.shape[:3], np.inf)
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
        if group > 1:  # each pedestrian's k-th largest gap over its samples (rows not computed: inf)
            ped = ki // group
            new = np.r_[True, (bi[1:] != bi[:-1]) | (mi[1:] != mi[:-1]) | (ped[1:] != ped[:-1])]
            table = np.full((int(np.count_nonzero(new)), group, dist.shape[1]), np.inf)
            table[np.cumsum(new) - 1, ki % group] = dist
            dist = np.partition(table, group - keep, axis=1)[:, group - keep]
            bi, mi = bi[new], mi[new]
        starts = np.flatnonzero(np.r_[True, (bi[1:] != bi[:-1]) | (mi[1:] != mi[:-1])])
        gap[bi[starts], mi[starts]] = np.minimum.reduceat(dist, starts, axis=0) - self.r_sum
        return gap

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        cfg = self.cfg
        robot = obs["robot"]
        b_all = len(robot)
        goal, dist, cap = _goal_velocity(robot, cfg)  # goal relative to the robot
        fut, mask = self.futures(obs)
        group = fut.shape[1] // cfg.num_pedestrians if self.samples else 1  # rows per pedestrian: its samples
        grow = self.step_inflation(obs) if group == 1 else np.zeros((b_all, fut.shape[1], self.lookahead))
        scale = np.divide(cap, dist, out=np.zeros_like(dist), where=dist >= 1e-9)
        chosen = goal * scale[:, None]  # no pedestrian observed: straight at the goal
        todo = np.flatnonzero(mask.any(axis=1) & (dist >= 1e-9))
        chunk = max(1, _SAMPLED_ROWS_CHUNK // group) if group > 1 else _SEARCH_CHUNK  # bounded memory for large batches
        for lo in range(0, len(todo), chunk):
            rows = todo[lo : lo + chunk]
            chosen[rows] = self._search(goal[rows], fut[rows], mask[rows], grow[rows], group)
        return velocities_to_actions(chosen, robot.reshape(b_all, -1), cfg)

    def _search(
        self, goal: np.ndarray, fut: np.ndarray, mask: np.ndarray, grow: np.ndarray, group: int = 1
    ) -> np.ndarray:
        """First velocities ``(B, 2)`` of the best plans (goal ``(B, 2)`` and futures relative to the robot; ``grow``
        ``(B, K, L)``: :meth:`step_inflation`; ``group``: consecutive rows per pedestrian, its samples)."""
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
            gap = self._gaps(x, valid, move, fut[:, :, h], fut[:, :, h + 1], mask, inflate, group)
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
