"""Running policies on environments: the policy adapter, the fixed episode lists, episodes in lockstep.

What evaluation, validation during training and the warm start share:

- :func:`evaluation_seeds`: the fixed, seeded episode list of a split, the same for every arm and policy (so
  comparisons are paired);
- :func:`run_episodes`: one episode per seed, several environments stepped in lockstep in this process with one
  batched ``predict`` per step (SB3's batched ``predict``; the planners score candidates for the whole batch at
  once). Each episode depends only on its seed, so the result does not depend on how many environments run side
  by side. An episode gives one row (:func:`episode_row`, columns :data:`EPISODE_COLUMNS`);
- :class:`SB3Policy`: an SB3 model (and its ``VecNormalize`` statistics) behind that ``predict``;
- :func:`prepare_forecasts`: the shared on-disk forecast cache filled before the environments are made.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn.data.constants import SPLITS
from envs.config import config_from

#: Per-episode metrics of a row (averaged, with bootstrap intervals, by :func:`agents.evaluation.summary.summarise`);
#: each is a key of ``info["episode_metrics"]`` (:meth:`envs.rewards.EpisodeMetrics.summary`).
METRICS: Final[tuple[str, ...]] = (
    "navigation_time_s",
    "path_length_m",
    "path_ratio",
    "path_ratio_required",
    "spl",
    "min_gap_m",
    "min_clearance_m",
    "min_ttc_s",
    "discomfort_frequency",
    "intrusion_ratio",
    "mean_speed_mps",
    "mean_accel_mps2",
    "mean_jerk_mps3",
    "forecast_ade_m",
    "forecast_fde_m",
    "crowd_density",
    "steps",
    "return",
)
#: Metrics added after results were committed (issue 31). Episode files and archives written before them lack their
#: columns; there they read as *absent* -- left out of summaries and archives (:func:`recorded_metrics`) -- rather
#: than as undefined, so the summaries of those files stay what they were.
ADDED_METRICS: Final[tuple[str, ...]] = (
    "path_ratio_required",
    "spl",
    "min_clearance_m",
    "min_ttc_s",
    "mean_speed_mps",
    "mean_accel_mps2",
)


def recorded_metrics(rows: Sequence[Mapping[str, Any]]) -> tuple[str, ...]:
    """:data:`METRICS` that ``rows`` record: all but the :data:`ADDED_METRICS` no row has a key for (in order)."""
    return tuple(m for m in METRICS if m not in ADDED_METRICS or any(m in r for r in rows))


#: What the robot did to people (issue 28; ``envs.reaction.DisturbanceMetrics``, in ``info["episode_metrics"]`` when the
#: environment's pedestrians may react; 0 under ``reaction="none"``). Blank in a row when the environment does not
#: report them: absent, not zero.
DISTURBANCE_METRICS: Final[tuple[str, ...]] = (
    "ped_disturbed",
    "ped_deviation_mean_m",
    "ped_deviation_max_m",
    "ped_delay_s",
)
#: Columns of ``episodes.csv``, in order (the metrics before ``steps`` and ``return``, then the collision details and
#: the disturbance metrics).
EPISODE_COLUMNS: Final[tuple[str, ...]] = (
    *("episode", "seed", "recording", "t0_s", "outcome"),
    *METRICS[:-2],
    *(
        "pedestrians_near_path",
        "collisions",
        "collision_fault",
        "popin_events",
        *DISTURBANCE_METRICS,
        "steps",
        "return",
    ),
)


class SB3Policy:
    """An SB3 model (and its ``VecNormalize`` statistics, if it was trained with them) behind ``predict``.

    Args:
        model: a loaded SB3 algorithm, or an SB3 policy network (both have ``predict`` and ``observation_space``).
        vecnormalize: what normalises observations as the model was trained with: SB3's ``VecNormalize``, or its
            statistics as numbers (:class:`agents.policy_file.ObservationNormalizer`, from a policy file), or None.
        source: where the model came from (for messages).
    """

    def __init__(self, model: Any, vecnormalize: Any = None, source: str = "") -> None:
        self.model = model
        self.vecnormalize = vecnormalize
        self.source = source
        self.observation_space = model.observation_space

    def predict(
        self,
        obs: Mapping[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        if self.vecnormalize is not None:
            obs = self.vecnormalize.normalize_obs(dict(obs))
        return self.model.predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)


def evaluation_seeds(split: str, episodes: int, seed: int = 0) -> list[int]:
    """The fixed episode seeds of an evaluation: the same list for every arm and policy.

    Args:
        split: the split whose held-out scene is evaluated (each split has its own list).
        episodes: how many.
        seed: which list (0 is the reported one).

    Returns:
        ``episodes`` integers in ``[0, 2**31)``; the first ``n`` of a longer list equal a list of ``n``.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    if episodes < 0:
        raise ValueError(f"episodes must be >= 0, got {episodes!r}")
    rng = np.random.default_rng([int(seed), zlib.crc32(split.encode())])
    return [int(s) for s in rng.integers(0, 2**31, size=episodes)]


def prepare_forecasts(env_kwargs: Mapping[str, Any], progress: bool = False) -> dict[str, Any] | None:
    """Fill the shared on-disk forecast cache for the recordings environments of ``env_kwargs`` replay, so that no
    worker computes forecasts (:func:`envs.forecasting.build.build_forecast_cache`); None when there is nothing to build
    (no learned predictor, no disk cache, or a crowd that is not replayed from ETH/UCY).

    Raises:
        DataNotFoundError: the environments would replay ETH/UCY scenes and the data is not found (as they would).
    """
    import envs.forecasting.build as forecasts
    from crowdnav_mesrnn import predictors
    from envs.config import crowd_source, names_scene

    cfg = config_from(dict(env_kwargs), {})
    build = getattr(forecasts, "build_forecast_cache", None)
    learned = predictors.per_split(cfg.predictor)
    if build is None or not learned:
        return None
    if not (getattr(cfg, "cache_forecasts", True) and getattr(cfg, "forecast_disk_cache", True)):
        return None
    source = crowd_source(cfg, names_scene(None, env_kwargs))
    if source.kind != "replay":
        return None
    return build(
        cfg.predictor,
        cfg.split,
        cfg.part,
        memory=cfg.forecast_memory,
        data_dir=source.data_dir,
        cache_dir=getattr(cfg, "forecast_cache_dir", None),
        progress=progress,
    )


def episode_row(index: int, seed: int, reset_info: Mapping[str, Any], metrics: Mapping[str, Any], ret: float) -> dict:
    """One row of ``episodes.csv`` (see :data:`EPISODE_COLUMNS`)."""
    row: dict[str, Any] = {"episode": index, "seed": seed}
    row["recording"] = reset_info.get("recording")
    row["t0_s"] = reset_info.get("t0_s")
    for key in EPISODE_COLUMNS[4:-1]:
        row[key] = metrics.get(key, reset_info.get(key))
    row["return"] = float(ret)
    return row


StepHook = Callable[[int, Mapping[str, np.ndarray], np.ndarray, float, bool, bool], None]


def run_episodes(
    policy: Any,
    envs: Sequence[Any],
    seeds: Sequence[int],
    on_step: StepHook | None = None,
    progress: bool = False,
    deterministic: bool = True,
    desc: str = "episodes",
) -> list[dict[str, Any]]:
    """Run one episode per seed, stepping ``envs`` in lockstep with one batched ``predict`` per step.

    Args:
        policy: anything with SB3's ``predict`` accepting batched observation dicts. A policy with a ``bind_envs``
            method (the privileged planner, :mod:`agents.planners.privileged`) is given the environment of each row of
            the batch before each ``predict``.
        envs: environments of one configuration (each takes the next seed when its episode ends).
        seeds: episode ``k`` is ``reset(seed=seeds[k])``.
        on_step: called as ``on_step(k, obs, action, reward, terminated, truncated)`` after every step of
            episode ``k`` (``obs`` is the observation the action was taken on).
        progress: show a progress bar over episodes.
        deterministic: passed to ``predict``.
        desc: the progress bar's label, saying whose episodes it counts.

    Returns:
        one row per episode, in seed order (see :func:`episode_row`).
    """
    n = len(seeds)
    bind = getattr(policy, "bind_envs", None)
    rows: list[dict[str, Any] | None] = [None] * n
    active: dict[int, list[Any]] = {}  # env index -> [episode, obs, return, reset info]
    next_k = 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=desc, unit="episode", dynamic_ncols=True)

    def start(i: int) -> None:
        nonlocal next_k
        if next_k < n:
            obs, info = envs[i].reset(seed=int(seeds[next_k]))
            active[i] = [next_k, obs, 0.0, info]
            next_k += 1

    for i in range(min(len(envs), n)):
        start(i)
    while active:
        idx = list(active)
        first = active[idx[0]][1]
        batch = {key: np.stack([active[i][1][key] for i in idx]) for key in first}
        if bind is not None:
            bind([envs[i] for i in idx])
        actions, _ = policy.predict(batch, deterministic=deterministic)
        for j, i in enumerate(idx):
            k, obs, ret, rinfo = active[i]
            action = np.asarray(actions[j])
            obs_next, reward, terminated, truncated, info = envs[i].step(action)
            if on_step is not None:
                on_step(k, obs, action, float(reward), bool(terminated), bool(truncated))
            ret += float(reward)
            if terminated or truncated:
                rows[k] = episode_row(k, int(seeds[k]), rinfo, info["episode_metrics"], ret)
                del active[i]
                if bar is not None:
                    bar.update(1)
                start(i)
            else:
                active[i][1], active[i][2] = obs_next, ret
    if bar is not None:
        bar.close()
    return [r for r in rows if r is not None]
