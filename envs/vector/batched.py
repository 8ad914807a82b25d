"""``CrowdNav-MESRNN-v0`` batched: N episodes stepped in one call, identical to N single environments.

:class:`BatchedCrowdNavEnv` is the ``vector_entry_point`` of every environment id, so
``gymnasium.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point", **kwargs)`` makes it. It is the same
environment as :class:`envs.crowd_nav.CrowdNavEnv` (the reference, documented there): for the same seeds and
actions its observations, rewards, terminations, truncations and ``info`` equal those of
``gymnasium.vector.SyncVectorEnv`` over N single environments, bit for bit (``tests/envs/vector``).
"""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from crowdnav_mesrnn.data.constants import OBS_LEN
from envs.crowd_nav import _CONFIGURED, TIMING_KEYS, UNDISTURBED, CrowdNavEnv, reset_info, reset_options
from envs.episodes import Episode
from envs.forecasting.sources import TrueFuture, fill_forward
from envs.forecasting.uncertainty import UncertaintySource
from envs.forecasting.window import PredictorForecast
from envs.observation import nearest_visible
from envs.popin import POPIN_MARGIN_M, PopInRule
from envs.replay import TIME_TOL_S, Replay
from envs.rewards import REWARD_COMPONENTS, EpisodeMetrics, time_to_collision
from envs.timing import PhaseTimer, timed
from envs.vector.physics import MAX_WORLDS, BatchedWorld
from envs.vector.replay import BatchedReplay

#: ``rule._annotation`` is None (nobody dropped by perception).
_NO_ANNOTATION: Final[int] = -(2**62)


class _World:
    """One world's episode state, under the attribute names :class:`~envs.crowd_nav.CrowdNavEnv` uses (its
    ``_command`` and ``_forecast_errors`` run on it)."""

    def __init__(self, env: CrowdNavEnv) -> None:
        self.config = env.config
        self._substeps = env._substeps
        self._substep_s = env._substep_s
        self._heading = 0.0
        self._replay: Replay | None = None
        self._forecast_log: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._metrics: EpisodeMetrics | None = None
        self._reactive = None  # reaction "none": the replay is the world
        self.episode: Episode | None = None
        self.popin = PopInRule(env._r_sum + POPIN_MARGIN_M)
        self.touch_fault: dict[int, str] = {}
        self.np_random: np.random.Generator | None = None
        self.np_random_seed: int | None = None  # the seed np_random was made from (seeding.np_random's)
        self.forecast_rng: np.random.Generator | None = None
        self.collision_fault: str | None = None
        self.velocities: list[np.ndarray] = []
        self.last_rows = np.zeros(0, dtype=np.int64)
        self.last_forecasts: np.ndarray | None = None
        self.uncertainty: UncertaintySource | None = None  # the episode's radii (for_episode of the env's source)


class NotBatchedError(NotImplementedError, ValueError):
    """A setting the batched environment does not step (pedestrians that react, rendering): step single environments
    (:func:`envs.vector.make_vector_env` does so by itself, with a warning)."""


class BatchedCrowdNavEnv(VectorEnv):
    """N crowd-navigation episodes stepped at once: the environment of :class:`envs.crowd_nav.CrowdNavEnv`, batched.

    Everything the single environment documents holds for each of the N worlds: spaces (batched), episodes drawn
    from ``reset(seed=...)`` (an int seeds world ``i`` with ``seed + i``, as ``SyncVectorEnv`` does; a list gives
    one seed per world), ``reset(options=...)`` (the single environment's options, applied to every world reset,
    plus ``reset_mask``: a ``(N,)`` bool array of the worlds to reset), reward, termination, truncation and
    ``info`` (a dict of arrays with ``_key`` masks, as ``SyncVectorEnv`` builds it). Autoreset is Gymnasium's
    ``NEXT_STEP``: the step after a world's episode ends resets it (observation of the new episode, reward 0, not
    terminated or truncated, ``info`` of the reset). Identical episodes: for the same seeds and actions every output
    equals ``SyncVectorEnv`` over N ``CrowdNavEnv``, bit for bit.

    How: the N worlds share one pymunk space (:class:`envs.vector.physics.BatchedWorld`, kept apart by shape filters,
    every body's state written and read through :mod:`pymunk.batch`); replay look-ups, perception, the pop-in rule's
    common case, the nearest pedestrians, observations, reward, termination and episode metrics run as numpy over
    all worlds (:class:`envs.vector.replay.BatchedReplay`). What still runs per world in Python: drawing an episode
    at a reset, the forecast look-up (a cached table read per world; the noisy oracle's noise comes from each world's
    own generator), the robot's command from its action (``math`` functions, as the single environment), a step on
    which a pedestrian appears on the robot or a pop-in ghost exists, contacts, and an episode's end.

    Args:
        num_envs: N, at most 256 (worlds one pymunk space keeps apart).
        render_mode: only None (render a single environment to watch an episode).
        max_episode_steps: None, or truncate every episode at this many steps as Gymnasium's ``TimeLimit`` wrapper
            does around a single environment (``gymnasium.make_vec(id, ..., max_episode_steps=n)`` passes it): the
            step that reaches it is truncated, with the info of a step the environment did not end itself.
        config, predictor, crowd, **kwargs: as :class:`envs.crowd_nav.CrowdNavEnv`.

    Under ``reaction="none"`` (the only setting batched) the reset ``info`` names the reaction and its parameters and
    the episode metrics hold the undisturbed disturbance metrics (:data:`envs.crowd_nav.UNDISTURBED`), as the single
    environment's.

    Raises:
        NotImplementedError: a ``reaction`` other than ``none`` (pedestrians reacting to the robot are not batched;
            the message names the key and value and says to step single environments).
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        render_mode: str | None = None,
        config: Mapping[str, Any] | str | os.PathLike[str] | None = None,
        predictor: Any = _CONFIGURED,
        crowd: Any = None,
        **kwargs: Any,
    ) -> None:
        if not isinstance(num_envs, int | np.integer) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer in [1, {MAX_WORLDS}], got {num_envs!r}")
        if render_mode is not None:
            raise NotBatchedError(
                f"the batched environment does not render (render_mode={render_mode!r}); render a single "
                "CrowdNavEnv (gymnasium.make(id, render_mode=...)) to watch an episode"
            )
        #: at most this many steps per episode (None: the episode's own time limit only), as Gymnasium's
        #: ``TimeLimit`` wrapper of a single environment: ``gymnasium.make_vec(id, max_episode_steps=...)`` passes it
        self.max_episode_steps = check_max_episode_steps(kwargs.pop("max_episode_steps", None))
        #: the reference environment: its configuration, recordings, forecast source, sampler and constants
        self.env = CrowdNavEnv(config=config, predictor=predictor, crowd=crowd, **kwargs)
        if self.env.reaction != "none":
            self.env.close()
            raise NotBatchedError(
                f"config key 'reaction' = {self.env.reaction!r}: the batched environment replays the recordings only "
                "(reaction='none'); for reacting pedestrians step single environments: CrowdNavEnv, or "
                "gymnasium.make_vec(id, num_envs=N, vectorization_mode='sync') (a SyncVectorEnv)"
            )
        if num_envs > MAX_WORLDS:
            self.env.close()
            raise ValueError(
                f"num_envs must be an integer in [1, {MAX_WORLDS}] (the worlds one pymunk space keeps apart), got "
                f"{num_envs!r}; for more, step several batched environments or single ones "
                "(gymnasium.make_vec(id, num_envs=N, vectorization_mode='sync'))"
            )
        env = self.env
        cfg = self.config = env.config
        self.num_envs = n = int(num_envs)
        self.render_mode = None
        self.metadata = {**self.metadata, "render_fps": env.metadata["render_fps"]}
        self.single_observation_space = env.observation_space
        self.single_action_space = env.action_space
        self.observation_space = batch_space(env.observation_space, n)
        self.action_space = batch_space(env.action_space, n)
        self.forecaster = env.forecaster
        self.predictor_name = env.predictor_name
        self.with_forecasts = env.with_forecasts
        self.uncertainty = env.uncertainty
        self.samples = env.samples
        self.crowd_kind = env.crowd_kind
        self._worlds = [_World(env) for _ in range(n)]
        # Each world asks its own copy of the forecast and uncertainty sources: their memo tables (a time's resampled
        # forecasts, the resampling weights, the radii's weights) are keyed on rounded times but hold the values of
        # the first request, so a table shared by the worlds could differ in the last bits from what each single
        # environment computes for itself (its own first request).
        self._world_sources = [_own_memos(env.forecaster) for _ in range(n)]
        self._world_uncertainty = [_own_memos(env.uncertainty) for _ in range(n)]
        # what a world's source resampled, for the others to take when their inputs are equal bit for bit
        # (PredictorForecast.all_forecasts' ``shared``)
        self._shared_forecasts: dict[Any, Any] = {}
        self._timer = PhaseTimer(TIMING_KEYS)
        self._phys = BatchedWorld(n, cfg.robot_radius_m, cfg.pedestrian_radius_m)
        self._replay = BatchedReplay(n)
        self._s = env._substeps
        self._h = env._substep_s
        self._sub_offsets = env._sub_offsets
        self._obs_offsets = env._obs_offsets
        self._r_sum = env._r_sum
        self._near_m = env._near_m
        self._clear_m = env._r_sum + POPIN_MARGIN_M
        self._k = cfg.num_pedestrians
        self._hor = cfg.horizon_steps
        # per-world episode state
        self._n = np.zeros(n, dtype=np.int64)
        self._k0 = np.zeros(n, dtype=np.int64)
        self._on_grid = np.zeros(n, dtype=bool)
        self._t0 = np.zeros(n)
        self._max_steps = np.ones(n, dtype=np.int64)
        self._goal = np.zeros((n, 2))
        self._start = np.zeros((n, 2))
        self._velocity = np.zeros((n, 2))
        self._started = np.zeros(n, dtype=bool)
        self._autoreset = np.zeros(n, dtype=bool)
        # the pop-in rule's state in its common case (see _popin)
        self._pp_present = np.zeros((n, 1), dtype=bool)
        self._pp_any_ghost = np.zeros(n, dtype=bool)
        self._pp_ann = np.full(n, _NO_ANNOTATION, dtype=np.int64)
        self._pp_ann_ghost = np.zeros((n, 1), dtype=bool)
        self._reset_ghost = np.zeros((n, 1), dtype=bool)
        # episode metrics, summed as EpisodeMetrics.update does
        self._m_steps = np.zeros(n, dtype=np.int64)
        self._m_visible = np.zeros(n, dtype=np.int64)
        self._m_return = np.zeros(n)
        self._m_path = np.zeros(n)
        self._m_min_gap = np.full(n, math.inf)
        self._m_discomfort = np.zeros(n, dtype=np.int64)
        self._m_intrusion = np.zeros(n, dtype=np.int64)
        self._m_collisions = np.zeros(n, dtype=np.int64)
        self._m_jerk_sum = np.zeros(n)
        self._m_jerk_count = np.zeros(n, dtype=np.int64)
        self._m_vel = np.zeros((n, 3, 2))  # the last three step velocities (zeros before the first)
        self._m_accel_sum = np.zeros(n)
        self._m_min_ttc = np.full(n, math.inf)
        # the world at the last observation (CrowdNavEnv._last): pedestrians' velocities for the time to collision
        self._last_pos = np.zeros((n, 1, 2))
        self._last_present = np.zeros((n, 1), dtype=bool)
        self._obs: dict[str, np.ndarray] = {
            key: np.zeros((n, *space.shape), dtype=space.dtype) for key, space in self.single_observation_space.items()
        }

    # ------------------------------------------------------------------ public helpers

    @property
    def np_random_seed(self) -> tuple[int | None, ...]:  # type: ignore[override]
        """Each world's seed, as ``SyncVectorEnv`` gives its environments': the seed its generator was made from at
        its last seeded (or first) reset; None before its first reset."""
        return tuple(w.np_random_seed for w in self._worlds)

    @property
    def np_random(self) -> tuple[np.random.Generator | None, ...]:  # type: ignore[override]
        """Each world's generator (its episodes are drawn from it), as ``SyncVectorEnv`` gives its environments'."""
        return tuple(w.np_random for w in self._worlds)

    def precompute_forecasts(self, recording: str | None = None) -> int:
        """As :meth:`envs.crowd_nav.CrowdNavEnv.precompute_forecasts` (the forecast source is shared by all worlds)."""
        return self.env.precompute_forecasts(recording)

    @property
    def timings(self) -> dict[str, float]:
        """Seconds spent per phase (the single environment's :data:`~envs.crowd_nav.TIMING_KEYS`) since the last
        :meth:`reset_timings`, for all worlds together."""
        return self._timer.totals

    def reset_timings(self) -> None:
        self._timer.reset()

    @property
    def episodes(self) -> list[Episode | None]:
        """Each world's current episode (None before its first reset)."""
        return [w.episode for w in self._worlds]

    @property
    def robot_positions(self) -> np.ndarray:
        """``(N, 2)`` robot centres, metres."""
        return self._phys.robot_positions.copy()

    @property
    def steps_taken(self) -> np.ndarray:
        """``(N,)`` control steps taken in each world's current episode."""
        return self._n.copy()

    def observed_rows(self, world: int) -> np.ndarray:
        """Replay rows of the pedestrians in world ``world``'s last observation, in observation order."""
        return self._worlds[world].last_rows.copy()

    def last_forecasts(self, world: int) -> np.ndarray | None:
        """``(m, H, 2)`` world-frame forecasts of world ``world``'s observed pedestrians (before clipping), or None."""
        fc = self._worlds[world].last_forecasts
        return None if fc is None else fc.copy()

    def _times(self, worlds: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """Time of step ``steps`` of each world's episode, as ``CrowdNavEnv._time``."""
        dt = self.config.dt_s
        return np.where(self._on_grid[worlds], (self._k0[worlds] + steps) * dt, self._t0[worlds] + steps * dt)

    # ------------------------------------------------------------------ gym API

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        n = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * n
        elif isinstance(seed, int | np.integer) and not isinstance(seed, bool):
            seeds = [int(seed) + i for i in range(n)]
        else:
            good = isinstance(seed, Sequence | np.ndarray) and not isinstance(seed, str | bytes)
            seeds = list(seed) if good else []
            if not good or len(seeds) != n or not all(_is_seed(x) for x in seeds):
                raise ValueError(
                    f"seed must be None, an int or a sequence of {n} seeds (one per world, each an int or None), "
                    f"got {seed!r}"
                )
        if options is not None and not isinstance(options, Mapping):
            reset_options(options, self.config.goal_tolerance_m)  # raises, naming the allowed keys
        opts = dict(options) if options is not None else None
        mask = np.ones(n, dtype=bool)
        if opts is not None and "reset_mask" in opts:
            mask = np.asarray(opts.pop("reset_mask"))
            if mask.shape != (n,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"options['reset_mask'] must be a ({n},) bool array with a True value, got {mask!r}")
        worlds = np.flatnonzero(mask)
        parsed = reset_options(opts, self.config.goal_tolerance_m)
        infos: dict[str, Any] = {}
        done: list[int] = []
        try:
            for w in worlds.tolist():
                infos = self._add_info(infos, self._start_world(w, seeds[w], parsed), w)
                done.append(w)
        finally:
            # a draw that fails for one world (a t0_s past its recording's end) leaves the worlds before it in their
            # new episodes, observed, and the others as they were: SyncVectorEnv's state after the same error (which
            # also clears every world's autoreset flag; here a world the failed reset did not reach keeps its own)
            if done:
                started = np.asarray(done, dtype=np.int64)
                self._autoreset[started] = False
                self._observe_reset(started)
        return self._copy_obs(), infos

    def step(self, actions: Any) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        n = self.num_envs
        if not self._started.all():
            raise RuntimeError("call reset() before step()")
        acts = self._parse_actions(actions)
        resetting = self._autoreset.copy()
        infos: dict[str, Any] = {}
        for w in np.flatnonzero(resetting).tolist():
            infos = self._add_info(infos, self._start_world(w, None, {}), w)
        stepping = np.flatnonzero(~resetting)
        all_w = np.arange(n)
        s = self._s
        # the robots' commands (math, per world, as the single environment)
        commands = np.zeros((n, s, 2))
        act_list = acts.tolist()
        for w in stepping.tolist():
            ax, ay = act_list[w]
            commands[w] = CrowdNavEnv._command(self._worlds[w], (ax, ay))  # type: ignore[arg-type]
        # replay at the substep ends of the step (resetting worlds: at t0 last); _observe looks up the future
        t_now = self._times(all_w, self._n)
        t_next = np.where(resetting, t_now, self._times(all_w, self._n + 1))
        pos_times = np.concatenate([t_now[:, None] + self._sub_offsets[None, :], t_next[:, None]], axis=1)
        pos, present = self._positions(all_w, pos_times)  # (N, S + 1, P, 2)
        robot0 = self._phys.robot_positions.copy()
        path = np.empty((n, s + 1, 2))  # as CrowdNavEnv._robot_path (p += v * h)
        path[:, 0] = robot0
        for k in range(s):
            path[:, k + 1] = path[:, k] + commands[:, k] * self._h
        sub_pos = pos[:, : s + 1]
        sub_present = present[:, : s + 1].copy()
        sub_present[resetting] = False
        ghost = self._popin(stepping, pos_times[:, : s + 1], sub_pos, present[:, : s + 1], path)
        if ghost is not None:
            sub_present &= ~ghost
        near = self._near(sub_pos, sub_present, robot0)
        robot_path, contacts, touched = self._move(commands, sub_pos, sub_present, near)
        collided = np.zeros(n, dtype=bool)
        faults: list[str | None] = [None] * n
        new_contacts = np.zeros(n, dtype=np.int64)
        busy = set(contacts) | set(touched) | {w for w in stepping.tolist() if self._worlds[w].touch_fault}
        for w in sorted(busy):
            world = self._worlds[w]
            events = contacts.get(w, [])
            touching = touched.get(w, frozenset())
            for c in events:
                world.touch_fault.setdefault(c.row, c.fault)
            world.touch_fault = {r: f for r, f in world.touch_fault.items() if r in touching}
            fault = events[0].fault if events else next(iter(world.touch_fault.values()), None)
            collided[w] = bool(events) or bool(touching)
            faults[w] = fault if collided[w] else None
            new_contacts[w] = len(events)
        gap_step = self._gap_during(sub_pos, sub_present, near, robot_path)
        after = robot_path[:, -1]
        self._n[stepping] += 1
        self._velocity[stepping] = (after[stepping] - robot0[stepping]) / self.config.dt_s
        # the observation of every world: stepping ones at their step's end, resetting ones at t0
        obs_present = sub_present[:, s].copy()
        if resetting.any():
            obs_present[resetting] = present[resetting, s] & ~self._reset_ghost[resetting, : present.shape[2]]
        gap_now, intruding, visible, ttc = self._observe(all_w, t_next, pos[:, s], obs_present, after)
        rewards = np.zeros(n)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        if len(stepping):
            r, te, tr = self._reward(stepping, robot0, after, gap_step, gap_now, intruding, visible, ttc, collided,
                                     faults, new_contacts, infos)  # fmt: skip
            rewards[stepping], terminated[stepping], truncated[stepping] = r, te, tr
            if self.max_episode_steps is not None:  # TimeLimit's rule: truncated once the step count reaches it
                truncated[stepping] |= self._n[stepping] >= self.max_episode_steps
        self._autoreset = terminated | truncated
        return self._copy_obs(), rewards, terminated, truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        self.env.close()

    # ------------------------------------------------------------------ resets

    @timed("reset")
    def _start_world(self, w: int, seed: int | None, opts: dict[str, Any]) -> dict[str, Any]:
        """Draw world ``w``'s next episode as ``CrowdNavEnv.reset`` does; returns its reset ``info``."""
        world = self._worlds[w]
        cfg = self.config
        if seed is not None or world.np_random is None:
            world.np_random, world.np_random_seed = seeding.np_random(seed)
            try:
                world.forecast_rng = world.np_random.spawn(1)[0]
            except (TypeError, ValueError):  # a generator without a seed sequence
                world.forecast_rng = np.random.default_rng(int(world.np_random.integers(2**63)))
        ep = self.env.sampler.sample(world.np_random, **opts)
        world.episode = ep
        history_s = (OBS_LEN - 1) * ep.recording.step_s
        replay = Replay(ep.recording, ep.t0_s - history_s, ep.t0_s + (ep.max_steps + 1 + cfg.horizon_steps) * cfg.dt_s)
        world._replay = replay
        self._replay.set_world(w, replay)
        self._phys.reset_world(w, ep.start, replay.num_pedestrians)
        self._fit_width()
        self._n[w] = 0
        k0 = round(ep.t0_s / cfg.dt_s)
        self._k0[w] = k0
        self._on_grid[w] = abs(ep.t0_s - k0 * cfg.dt_s) < 1e-9
        self._t0[w] = ep.t0_s
        self._max_steps[w] = ep.max_steps
        self._goal[w] = ep.goal
        self._start[w] = ep.start
        self._velocity[w] = 0.0
        world._heading = math.atan2(ep.goal[1] - ep.start[1], ep.goal[0] - ep.start[0])
        world._forecast_log = []
        world.touch_fault = {}
        world.collision_fault = None
        self._m_steps[w] = self._m_visible[w] = self._m_discomfort[w] = self._m_intrusion[w] = 0
        self._m_collisions[w] = self._m_jerk_count[w] = 0
        self._m_return[w] = self._m_path[w] = self._m_jerk_sum[w] = self._m_accel_sum[w] = 0.0
        self._m_min_ttc[w] = math.inf
        self._m_min_gap[w] = math.inf
        self._m_vel[w] = 0.0
        t0 = float(self._times(np.array([w]), np.zeros(1, dtype=np.int64))[0])
        world.popin.reset(replay, t0, ep.start)
        if self.uncertainty is not None:
            world.uncertainty = self._world_uncertainty[w].for_episode(replay, replay.perceived_at(t0).index)
        self._sync_popin(w)
        nrow = replay.num_pedestrians
        self._reset_ghost[w] = False
        self._reset_ghost[w, :nrow] = world.popin.ghost
        self._started[w] = True
        return reset_info(ep, self.crowd_kind, self.predictor_name, self.env.reaction, cfg.reaction_params)

    def _fit_width(self) -> None:
        """Widen the per-row state to the replays' padded width P."""
        p = self._replay.width
        for name in ("_pp_present", "_pp_ann_ghost", "_reset_ghost", "_last_present", "_last_pos"):
            old = getattr(self, name)
            if old.shape[1] < p:
                grown = np.zeros((self.num_envs, p, *old.shape[2:]), dtype=old.dtype)
                grown[:, : old.shape[1]] = old
                setattr(self, name, grown)

    def _observe_reset(self, worlds: np.ndarray) -> None:
        """The first observation of the episodes just drawn in ``worlds``."""
        t0 = self._times(worlds, np.zeros(len(worlds), dtype=np.int64))
        pos, present = self._positions(worlds, t0[:, None])
        present[:, 0] &= ~self._reset_ghost[worlds, : present.shape[2]]
        self._observe(worlds, t0, pos[:, 0], present[:, 0], self._start[worlds])

    # ------------------------------------------------------------------ the phases of a step

    @timed("replay")
    def _positions(self, worlds: np.ndarray, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._replay.positions_at(worlds, times_s)

    @timed("physics")
    def _move(
        self, commands: np.ndarray, positions: np.ndarray, present: np.ndarray, near: np.ndarray
    ) -> tuple[np.ndarray, dict[int, list[Any]], dict[int, frozenset[int]]]:
        out = self._phys.step(commands, positions, present, near, self._h)
        self._phys.end_step()
        return out

    def _parse_actions(self, actions: Any) -> np.ndarray:
        """``(N, 2)`` float64 actions clipped to [-1, 1], as ``CrowdNavEnv._parse_action`` for each world. The action
        of a world reset in this step (``NEXT_STEP`` autoreset) is ignored, as ``SyncVectorEnv`` ignores it: it need
        not be finite."""
        n = self.num_envs
        try:
            a = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"actions must be {n} x 2 numbers in [-1, 1], got {actions!r}") from None
        if a.shape != (n, 2):
            raise ValueError(f"actions must have shape ({n}, 2), got shape {a.shape}")
        bad = ~np.isfinite(a).all(axis=1) & ~self._autoreset
        if bad.any():
            w = int(np.flatnonzero(bad)[0])
            raise ValueError(f"action of world {w} must be finite, got {actions[w]!r}")
        return np.minimum(np.maximum(a, -1.0), 1.0)

    def _sync_popin(self, w: int) -> None:
        """Copy world ``w``'s pop-in rule state into the batched arrays."""
        rule = self._worlds[w].popin
        nrow = len(rule.ghost)
        self._fit_width()
        self._pp_present[w] = False
        self._pp_present[w, :nrow] = rule._present
        self._pp_any_ghost[w] = rule._any_ghost
        self._pp_ann_ghost[w] = False
        if rule._annotation is None:
            self._pp_ann[w] = _NO_ANNOTATION
        else:
            index, cols, flags = rule._annotation
            self._pp_ann[w] = index
            self._pp_ann_ghost[w, cols] = flags

    @timed("physics")
    def _popin(
        self, stepping: np.ndarray, times: np.ndarray, positions: np.ndarray, present: np.ndarray, path: np.ndarray
    ) -> np.ndarray | None:
        """The pop-in rule over the step (:meth:`envs.popin.PopInRule.step` of every stepping world): its common case
        (no annotation inside the step, no ghost, nobody appearing on the robot) as numpy over the worlds, the rest
        through each world's own rule. Returns ``(N, S + 1, P)`` ghosts, or None when there is none."""
        if len(stepping) == 0:
            return None
        rp = self._replay
        s = self._s
        first = rp.frame_index(stepping, times[stepping][:, [0, s]])
        lo, hi = first[:, 0] + 1, first[:, 1] + 1
        at_lo = rp.times[stepping, np.minimum(lo, rp.times.shape[1] - 1)]
        inside = (hi > lo) & ~((hi - lo == 1) & (np.abs(at_lo - times[stepping, s]) <= TIME_TOL_S))
        pres = present[stepping]
        appear = (pres[:, 1:] & ~pres[:, :-1]).any(axis=1)  # (m, P)
        slow = inside | self._pp_any_ghost[stepping]
        cand = appear & ~slow[:, None]
        if cand.any():
            j, col = np.nonzero(cand)
            w = stepping[j]
            d = np.hypot(positions[w, 1:, col, 0] - path[w, 1:, 0], positions[w, 1:, col, 1] - path[w, 1:, 1])
            close = np.zeros(len(stepping), dtype=bool)
            np.logical_or.at(close, j, (d < self._clear_m).any(axis=1))
            slow |= close
        fast = stepping[~slow]
        self._pp_present[fast] = present[fast, s, : self._pp_present.shape[1]]
        with_ann = fast[(hi > lo)[~slow]]
        self._pp_ann[with_ann] = lo[~slow][(hi > lo)[~slow]]
        self._pp_ann_ghost[with_ann] = False
        ghost = None
        for w in stepping[slow].tolist():
            world = self._worlds[w]
            rule = world.popin
            nrow = int(rp.num_rows[w])
            rule._present = self._pp_present[w, :nrow].copy()
            g = rule.step(world._replay, times[w], positions[w, :, :nrow], present[w, :, :nrow], path[w])
            self._sync_popin(w)
            if g is not None:
                if ghost is None:
                    ghost = np.zeros(present.shape, dtype=bool)
                ghost[w, :, :nrow] = g
        return ghost

    @timed("physics")
    def _near(self, positions: np.ndarray, present: np.ndarray, robot: np.ndarray) -> np.ndarray:
        """``(N, P)``: rows within ``near_m`` of the robot's start of step at some substep boundary (as the single
        environment's ``hypot`` test; the coordinate bound first, which ``hypot`` can only exceed)."""
        r = self._near_m
        dx = positions[..., 0] - robot[:, None, None, 0]
        dy = positions[..., 1] - robot[:, None, None, 1]
        cand = present & (np.abs(dx) < r) & (np.abs(dy) < r)
        near = np.zeros(present.shape[::2], dtype=bool)
        if cand.any():
            w, k, col = np.nonzero(cand)
            hit = np.hypot(dx[w, k, col], dy[w, k, col]) < r
            near[w[hit], col[hit]] = True
        return near

    @timed("physics")
    def _gap_during(self, positions: np.ndarray, present: np.ndarray, near: np.ndarray, path: np.ndarray) -> np.ndarray:
        """``(N,)`` smallest surface gap to a near pedestrian at the substep ends after the step's start (inf: none)."""
        gap = np.full(self.num_envs, math.inf)
        w, col = np.nonzero(near)
        if len(w):
            d = np.hypot(positions[w, 1:, col, 0] - path[w, 1:, 0], positions[w, 1:, col, 1] - path[w, 1:, 1])
            d = np.where(present[w, 1:, col], d, math.inf).min(axis=1)
            np.minimum.at(gap, w, d)
            gap[np.unique(w)] -= self._r_sum
        return gap

    def _nearest(
        self, worlds: np.ndarray, robot: np.ndarray, positions: np.ndarray, perceived: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(rows (n, K) padded with 0, counts (n,))``: :func:`envs.observation.nearest_visible` of each world."""
        cfg = self.config
        k = self._k
        d = np.hypot(positions[..., 0] - robot[:, None, 0], positions[..., 1] - robot[:, None, 1])
        d = np.where(perceived, d, math.inf)
        cand = (d <= cfg.sensor_range_m).sum(axis=1)
        width = d.shape[1]
        if width > k + 1:  # the K + 1 nearest in any order, then by distance and row (a stable sort of all rows)
            part = np.argpartition(d, k, axis=1)[:, : k + 1]
        else:
            part = np.broadcast_to(np.arange(width), d.shape)
        order = np.take_along_axis(part, np.lexsort((part, np.take_along_axis(d, part, axis=1)), axis=-1), axis=1)
        rows = order[:, :k]
        if rows.shape[1] < k:
            rows = np.pad(rows, ((0, 0), (0, k - rows.shape[1])))
        counts = np.minimum(cand, k)
        # the single environment picks among more than K candidates with argpartition: with equal distances among
        # the K + 1 nearest its choice and order are argpartition's, so such worlds take its own function
        dsel = np.take_along_axis(d, order[:, : k + 1], axis=1)
        tied = (cand > k) & (dsel[:, 1:] == dsel[:, :-1]).any(axis=1) if dsel.shape[1] > 1 else np.zeros(len(d), bool)
        for j in np.flatnonzero(tied).tolist():
            w = int(worlds[j])
            nrow = int(self._replay.num_rows[w])
            r, _ = nearest_visible(robot[j], positions[j, :nrow], perceived[j, :nrow], cfg.sensor_range_m, k)
            rows[j, : len(r)] = r
        return rows, counts

    @timed("observation")
    def _observe(
        self, worlds: np.ndarray, t_s: np.ndarray, p_now: np.ndarray, pres_now: np.ndarray, robot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Perception at ``t_s`` of ``worlds`` (``CrowdNavEnv._observe`` of each): writes their observations; returns
        ``(gap at t_s (n,), intruding (n,), pedestrians perceived (n,), time to collision at t_s (n,), inf for a world
        just reset)``.

        Args:
            p_now: ``(n, P, 2)`` replay metres at ``t_s``; pres_now: ``(n, P)`` the pedestrians in the world then
                (pop-in ghosts removed). Their future (at ``t_s + h * dt_s``, ``h = 1..H``) is looked up here, for
                the present rows only (and for every row when the forecast source needs the true future).
            robot: ``(n, 2)`` robot positions.
        """
        index, age, seen_pos, seen_vel, seen_present = self._replay.perceived_at(worlds, t_s)
        dropped = (self._pp_ann[worlds] == index)[:, None] & self._pp_ann_ghost[worlds, : seen_present.shape[1]]
        perceived = seen_present & ~dropped
        rows, counts = self._nearest(worlds, robot, seen_pos, perceived)
        # the world at t_s: gap, and intrusion on a present pedestrian's true future path
        d_now = np.hypot(p_now[..., 0] - robot[:, None, 0], p_now[..., 1] - robot[:, None, 1])
        gap = np.where(pres_now, d_now, math.inf).min(axis=1) - self._r_sum
        ttc = np.full(len(worlds), math.inf)
        after_step = self._n[worlds] > 0
        if after_step.any():
            ttc[after_step] = self._time_to_collision(
                worlds[after_step], robot[after_step], p_now[after_step], pres_now[after_step]
            )
        width = p_now.shape[1]
        self._last_pos[worlds, :width] = p_now
        self._last_present[worlds] = False
        self._last_present[worlds, :width] = pres_now
        future_s = t_s[:, None] + self._obs_offsets[None, 1:]
        j, col = np.nonzero(pres_now)
        f_pos, f_present = self._rows_positions(worlds, future_s, j, col)  # (m, H, 2), (m, H)
        fx = f_pos[..., 0] - robot[j, None, 0]
        fy = f_pos[..., 1] - robot[j, None, 1]
        r = self._r_sum
        cand = f_present & (np.abs(fx) < r) & (np.abs(fy) < r)
        intruding = np.zeros(len(worlds), dtype=bool)
        if cand.any():
            i, h = np.nonzero(cand)
            hit = np.hypot(fx[i, h], fy[i, h]) < r
            intruding[j[i[hit]]] = True
        # the observation
        nw, k = len(worlds), self._k
        sel = np.arange(k)[None, :] < counts[:, None]
        jj = np.arange(nw)[:, None]
        ped_pos = seen_pos[jj, rows]  # (n, K, 2)
        ped_vel = seen_vel[jj, rows]
        b = self.env._builder
        robot_vel = self._velocity[worlds]
        obs_robot = np.empty((nw, b.robot_size), dtype=np.float32)
        g, v = b.goal_clip, b.speed
        obs_robot[:, 0:2] = np.minimum(np.maximum(self._goal[worlds] - robot, -g), g)
        obs_robot[:, 2:4] = np.minimum(np.maximum(robot_vel, -v), v)
        extra = 4
        if b.unicycle:
            headings = [self._worlds[w]._heading for w in worlds.tolist()]
            obs_robot[:, 4] = [math.cos(h) for h in headings]
            obs_robot[:, 5] = [math.sin(h) for h in headings]
            extra = 6
        if b.time_left:
            left = 1.0 - self._n[worlds] / self._max_steps[worlds]
            obs_robot[:, extra] = np.minimum(np.maximum(left, 0.0), 1.0)
            extra += 1
        if b.age:
            obs_robot[:, extra] = np.minimum(np.maximum(age, 0.0), 1.0)
        peds = np.zeros((nw, k, 4), dtype=np.float32)
        rel = _clip(ped_pos - robot[:, None, :], b.sensor)
        rvel = _clip(_clip(ped_vel.copy(), b.max_ped_speed) - robot_vel[:, None, :], b.rel_speed)
        peds[:, :, 0:2] = np.where(sel[..., None], rel, 0.0)
        peds[:, :, 2:4] = np.where(sel[..., None], rvel, 0.0)
        obs = self._obs
        obs["robot"][worlds] = obs_robot
        obs["pedestrians"][worlds] = peds.reshape(nw, -1) if b.flat else peds
        obs["mask"][worlds] = sel.astype(np.int8)
        rows_of = [rows[j, : counts[j]] for j in range(nw)]
        for j, w in enumerate(worlds.tolist()):
            world = self._worlds[w]
            world.last_rows = rows_of[j]
            world.last_forecasts = None
        if self.with_forecasts:
            self._forecasts(worlds, t_s, future_s, rows_of, seen_pos, p_now, pres_now, index, age, robot)
        return gap, intruding, counts, ttc

    def _time_to_collision(
        self, worlds: np.ndarray, robot: np.ndarray, p_now: np.ndarray, pres_now: np.ndarray
    ) -> np.ndarray:
        """``(n,)`` each world's smallest constant-velocity time to collision at the end of its step
        (``CrowdNavEnv._time_to_collision``): the pedestrians' velocities over the step from the last observation's
        world (0 for one that was not there), every present row's :func:`envs.rewards.time_to_collision` at once.

        Args:
            robot: ``(n, 2)`` robot positions; p_now: ``(n, P, 2)`` pedestrians, metres; pres_now: ``(n, P)``.
        """
        out = np.full(len(worlds), math.inf)
        j, col = np.nonzero(pres_now)
        if len(j):
            w = worlds[j]
            p = p_now[j, col]
            both = self._last_present[w, col][:, None]  # (present now, by the nonzero)
            velocity = np.where(both, (p - np.where(both, self._last_pos[w, col], p)) / self.config.dt_s, 0.0)
            rel_p = p - robot[j]
            rel_v = velocity - self._velocity[w]
            np.minimum.at(out, j, time_to_collision(rel_p, rel_v, self._r_sum))
        return out

    @timed("replay")
    def _rows_positions(
        self, worlds: np.ndarray, times_s: np.ndarray, which: np.ndarray, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        return self._replay.rows_at(worlds, times_s, which, rows)

    @timed("forecasts")
    def _forecasts(
        self,
        worlds: np.ndarray,
        t_s: np.ndarray,
        future_s: np.ndarray,
        rows_of: list[np.ndarray],
        seen_pos: np.ndarray,
        p_now: np.ndarray,
        pres_now: np.ndarray,
        index: np.ndarray,
        age: np.ndarray,
        robot: np.ndarray,
    ) -> None:
        """Each world's forecasts of its perceived pedestrians (``CrowdNavEnv._forecast``), into the observation.

        Args:
            future_s: ``(n, H)`` the forecast times; p_now, pres_now: ``(n, P, 2)``, ``(n, P)`` the world at ``t_s``.
        """
        b = self.env._builder
        k, hor = self._k, self._hor
        nw = len(worlds)
        fc_obs = np.zeros((nw, k, hor, 2), dtype=np.float32)
        unc_obs = np.zeros((nw, k, hor), dtype=np.float32) if b.with_uncertainty else None
        smp_obs = np.zeros((nw, k, b.samples, hor, 2), dtype=np.float32) if b.samples else None
        source = self.forecaster
        times = t_s.tolist()
        if isinstance(source, PredictorForecast) and unc_obs is None and smp_obs is None:
            self._table_forecasts(worlds, times, rows_of, robot, fc_obs)
            obs = self._obs
            obs["forecasts"][worlds] = fc_obs.reshape(nw, -1) if b.flat else fc_obs
            return
        if source.needs_truth:
            positions, present = self._positions(worlds, future_s)  # (n, H, P, 2)
        for j, w in enumerate(worlds.tolist()):
            rows = rows_of[j]
            m = len(rows)
            if m == 0:
                continue
            world = self._worlds[w]
            truth = None
            if source.needs_truth:
                future, valid = positions[j][:, rows].transpose(1, 0, 2), present[j][:, rows].T
                current = np.where(pres_now[j, rows, None], p_now[j, rows], seen_pos[j, rows])
                truth = TrueFuture(fill_forward(future, valid, current), valid)
            own = self._world_sources[w]
            fc = own.forecast(world._replay, times[j], rows, truth, world.forecast_rng)  # type: ignore[arg-type,union-attr]
            if fc is None:
                continue
            world._forecast_log.append((times[j], rows, fc))
            world.last_forecasts = fc
            fc_obs[j, :m] = _clip(fc - robot[j], b.fc_bound)
            if unc_obs is not None and world.uncertainty is not None:
                unc = world.uncertainty.radius(world._replay, times[j], rows, float(age[j]), int(index[j]))  # type: ignore[arg-type]
                unc_obs[j, :m] = np.clip(unc, 0.0, b.fc_bound)
            if smp_obs is not None and self.samples is not None:
                smp = self.samples.draw(world._replay, times[j], rows)  # type: ignore[arg-type]
                smp_obs[j, :m] = _clip(smp - robot[j], b.fc_bound)
        obs = self._obs
        obs["forecasts"][worlds] = fc_obs.reshape(nw, -1) if b.flat else fc_obs
        if unc_obs is not None:
            obs["forecast_uncertainty"][worlds] = unc_obs.reshape(nw, -1) if b.flat else unc_obs
        if smp_obs is not None:
            obs["forecast_samples"][worlds] = smp_obs.reshape(nw, -1) if b.flat else smp_obs

    def _table_forecasts(
        self, worlds: np.ndarray, times: list[float], rows_of: list[np.ndarray], robot: np.ndarray, out: np.ndarray
    ) -> None:
        """A predictor's forecasts (:class:`~envs.forecasting.window.PredictorForecast`, whose ``forecast`` takes the
        perceived pedestrians' rows of its per-time table) for every world in one look-up: each world's table at its
        time, then one search of all the worlds' rows in them. Writes the clipped offsets into ``out``
        ``(n, K, H, 2)`` and logs each world's forecasts."""
        source = self.forecaster
        assert isinstance(source, PredictorForecast)
        counts = np.array([len(r) for r in rows_of])
        js = np.flatnonzero(counts)
        if len(js) == 0:
            return
        shared = self._shared_forecasts
        tables = [
            self._world_sources[w].all_forecasts(self._worlds[w]._replay, times[j], shared)  # type: ignore[union-attr]
            for j, w in zip(js.tolist(), worlds[js].tolist(), strict=True)
        ]  # type: ignore[arg-type]
        sizes = np.array([len(c) for c, _ in tables])
        rank = np.repeat(np.arange(len(js)), counts[js])
        big = int(self._replay.columns.max()) + 1 if self._replay.columns.size else 1
        keys = np.concatenate([c for c, _ in tables]) + np.repeat(np.arange(len(js)) * big, sizes)
        rows = np.concatenate([rows_of[j] for j in js.tolist()])
        want = self._replay.columns[worlds[js][rank], rows] + rank * big
        idx = np.minimum(np.searchsorted(keys, want), max(len(keys) - 1, 0))
        if len(keys) == 0 or not np.array_equal(keys[idx], want):
            bad = int(rank[np.flatnonzero(keys[idx] != want)[0]]) if len(keys) else 0
            raise RuntimeError(
                f"forecast requested for pedestrians not perceived at t={times[int(js[bad])]:.3f} s in "
                f"{self._worlds[int(worlds[js[bad]])]._replay.name}"  # type: ignore[union-attr]
            )
        fc = np.concatenate([f for _, f in tables])[idx]  # (M, H, 2)
        slot = np.arange(len(rows)) - np.repeat(np.cumsum(counts[js]) - counts[js], counts[js])
        out[js[rank], slot] = _clip(fc - robot[js[rank]][:, None, :], self.env._builder.fc_bound)
        bounds = np.cumsum(counts[js]).tolist()
        lo = 0
        for j, hi in zip(js.tolist(), bounds, strict=True):
            world = self._worlds[int(worlds[j])]
            world._forecast_log.append((times[j], rows_of[j], fc[lo:hi]))
            world.last_forecasts = fc[lo:hi]
            lo = hi

    @timed("reward")
    def _reward(
        self,
        ws: np.ndarray,
        before_all: np.ndarray,
        after_all: np.ndarray,
        gap_step: np.ndarray,
        gap_now: np.ndarray,
        intruding_all: np.ndarray,
        visible: np.ndarray,
        ttc: np.ndarray,
        collided_all: np.ndarray,
        faults: list[str | None],
        new_contacts: np.ndarray,
        infos: dict[str, Any],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reward, termination, truncation, ``info`` and episode metrics of the stepping worlds ``ws``
        (``CrowdNavEnv._reward`` of each)."""
        cfg = self.config
        n = self.num_envs
        before, after = before_all[ws], after_all[ws]
        goal = self._goal[ws]
        min_gap = np.minimum(gap_step[ws], gap_now[ws])
        collided = collided_all[ws]
        intruding = intruding_all[ws]
        gb, ga = (goal - before).tolist(), (goal - after).tolist()
        dist_before = np.array([math.hypot(x, y) for x, y in gb])
        dist_after = np.array([math.hypot(x, y) for x, y in ga])
        step_m = np.array([math.hypot(x, y) for x, y in (after - before).tolist()])
        reached = dist_after <= cfg.goal_tolerance_m
        comps = {
            "success": np.where(reached & ~collided, float(cfg.success_reward), 0.0),
            "collision": np.where(collided, float(cfg.collision_penalty), 0.0),
            "discomfort": np.where(
                ~collided & (min_gap < cfg.discomfort_dist_m),
                (np.maximum(min_gap, 0.0) - cfg.discomfort_dist_m) * cfg.discomfort_scale * cfg.dt_s,
                0.0,
            ),
            "progress": cfg.progress_weight * (cfg.progress_gamma * -dist_after + dist_before),
            "intrusion": np.where(intruding, float(cfg.intrusion_penalty), 0.0),
            "time": np.full(len(ws), float(cfg.time_penalty)),
        }
        reward = np.zeros(len(ws))
        for key in REWARD_COMPONENTS:
            reward = reward + comps[key]
        terminated = (collided & cfg.terminate_on_collision) | (reached & ~collided)
        steps = self._n[ws]
        truncated = ~terminated & (steps >= self._max_steps[ws])
        # episode metrics (EpisodeMetrics.update)
        self._m_steps[ws] += 1
        self._m_min_ttc[ws] = np.minimum(self._m_min_ttc[ws], ttc[ws])
        self._m_visible[ws] += visible[ws]
        self._m_return[ws] += reward
        self._m_path[ws] += step_m
        self._m_min_gap[ws] = np.minimum(self._m_min_gap[ws], min_gap)
        self._m_discomfort[ws] += min_gap < cfg.discomfort_dist_m
        self._m_intrusion[ws] += intruding
        self._m_collisions[ws] += new_contacts[ws]
        for w in ws.tolist():
            if faults[w] is not None and self._worlds[w].collision_fault is None:
                self._worlds[w].collision_fault = faults[w]
        vel = self._m_vel[ws]
        vel = np.concatenate([vel[:, 1:], self._velocity[ws][:, None, :]], axis=1)
        self._m_vel[ws] = vel
        accel = (vel[:, 2] - vel[:, 1]) / cfg.dt_s
        self._m_accel_sum[ws] += np.hypot(accel[:, 0], accel[:, 1])
        jerk_on = self._m_steps[ws] >= 2
        if jerk_on.any():
            jv = vel[jerk_on]
            jerk = (jv[:, 2] - 2 * jv[:, 1] + jv[:, 0]) / cfg.dt_s**2
            idx = ws[jerk_on]
            self._m_jerk_sum[idx] += np.hypot(jerk[:, 0], jerk[:, 1])
            self._m_jerk_count[idx] += 1
        # info, as SyncVectorEnv gathers the single environments' dicts
        mask = np.zeros(n, dtype=bool)
        mask[ws] = True
        gaps = min_gap.tolist()
        first_gap = gaps[0]

        def column(values: Any, dtype: Any) -> np.ndarray:
            out = np.zeros(n, dtype=dtype) if dtype is not object else np.full(n, None, dtype=object)
            out[ws] = values
            return out

        times = [round(int(s) * cfg.dt_s, 9) for s in steps.tolist()]
        step_info: dict[str, Any] = {
            "time_s": column(times, np.float64),
            "distance_to_goal_m": column(dist_after, np.float64),
        }
        if math.isinf(first_gap):
            step_info["min_gap_m"] = column(np.array([None if math.isinf(x) else x for x in gaps], object), object)
        else:
            step_info["min_gap_m"] = column(np.where(np.isinf(min_gap), np.nan, min_gap), np.float64)
        step_info["collision"] = column(collided, bool)
        fault_vals = np.empty(len(ws), dtype=object)
        fault_vals[:] = [faults[w] for w in ws.tolist()]
        step_info["collision_fault"] = column(fault_vals, object)
        step_info["reached_goal"] = column(reached & ~collided, bool)
        rc: dict[str, Any] = {}
        for key in REWARD_COMPONENTS:
            rc[key] = column(comps[key], np.float64)
            rc[f"_{key}"] = mask.copy()
        step_info["reward_components"] = rc
        for key, value in step_info.items():
            infos[key] = value
            infos[f"_{key}"] = mask.copy()
        for j in np.flatnonzero(terminated | truncated).tolist():
            w = int(ws[j])
            if collided[j] and cfg.terminate_on_collision:
                outcome = "collision"
            elif reached[j] and not collided[j]:
                outcome = "success"
            else:
                outcome = "timeout"
            self._add_info(infos, {"episode_metrics": self._episode_metrics(w, outcome)}, w)
        return reward, terminated, truncated

    def _episode_metrics(self, w: int, outcome: str) -> dict[str, Any]:
        """World ``w``'s ``info["episode_metrics"]``: :meth:`envs.rewards.EpisodeMetrics.summary`, then the disturbance
        metrics of an episode in which nobody reacts (:data:`envs.crowd_nav.UNDISTURBED`), as the single environment."""
        world = self._worlds[w]
        ep = world.episode
        assert ep is not None
        cfg = self.config
        m = EpisodeMetrics.of_episode(ep, cfg.dt_s, cfg.discomfort_dist_m, cfg.goal_tolerance_m)
        m.steps = int(self._m_steps[w])
        m.visible_sum = int(self._m_visible[w])
        m.episode_return = float(self._m_return[w])
        m.path_length_m = float(self._m_path[w])
        m.min_gap_m = float(self._m_min_gap[w])
        m.discomfort_steps = int(self._m_discomfort[w])
        m.intrusion_steps = int(self._m_intrusion[w])
        m.collisions = int(self._m_collisions[w])
        m.collision_fault = world.collision_fault
        m.jerk_sum = float(self._m_jerk_sum[w])
        m.jerk_count = int(self._m_jerk_count[w])
        m.accel_sum = float(self._m_accel_sum[w])
        m.min_ttc_s = float(self._m_min_ttc[w])
        world._metrics = m
        CrowdNavEnv._forecast_errors(world)  # type: ignore[arg-type]
        m.popin_events = world.popin.events
        return {**m.summary(outcome, int(self._n[w]) * cfg.dt_s, self.with_forecasts), **UNDISTURBED}

    def _copy_obs(self) -> dict[str, np.ndarray]:
        return {key: value.copy() for key, value in self._obs.items()}


def check_max_episode_steps(value: Any) -> int | None:
    """``max_episode_steps`` checked: None or an integer >= 1 (``ValueError`` naming the key, value and what is
    allowed)."""
    if value is None:
        return None
    if not isinstance(value, int | np.integer) or isinstance(value, bool) or value < 1:
        raise ValueError(f"max_episode_steps must be None or an integer >= 1 (steps per episode), got {value!r}")
    return int(value)


def _is_seed(value: Any) -> bool:
    return value is None or (isinstance(value, int | np.integer) and not isinstance(value, bool))


def _clip(x: np.ndarray, bound: float) -> np.ndarray:
    """``x`` clipped to ``[-bound, bound]`` in place."""
    np.minimum(x, bound, out=x)
    np.maximum(x, -bound, out=x)
    return x


def _own_memos(source: Any) -> Any:
    """A shallow copy of a forecast or uncertainty source with empty memo tables of its own (``_cache``, the
    resampled forecasts per time, and ``_weights``, the resampling weights), sharing everything else (the per-chunk
    forecast tables, computed the same whoever asks first); ``source`` itself when it keeps no such memo."""
    memos = [name for name in ("_cache", "_weights") if isinstance(getattr(source, name, None), dict)]
    if not memos:
        return source
    own = copy.copy(source)
    for name in memos:
        setattr(own, name, {})
    return own
