"""Evaluate a policy — a training run, an SB3 model, or a planner — on a fixed, seeded list of episodes.

``python -m agents.evaluate RUN_DIR_OR_PLANNER --predictor mesrnn --split zara1 --episodes 500 --json``
(also ``crowdnav-mesrnn agent evaluate ...``) replays the split's held-out scene (``part="test"``) over
:func:`evaluation_seeds` — the same list for every arm and policy, so comparisons are paired — with
deterministic actions, and by default only episodes in which a pedestrian comes within sensor range
of the straight path (``require_pedestrians``). Per-episode metrics go to ``episodes.csv`` and the summary
to ``summary.json``, in ``--out`` or else a new ``runs/eval/<policy>_<predictor>_<split>_s<seed>_<UTC time>/``
(:func:`default_eval_dir`); the summary gives outcome rates with 95 % Wilson intervals and metric means with
bootstrap intervals (:mod:`agents.stats`).

Speed: several environments are stepped in lockstep in this process and the policy is called once
per step on their stacked observations (SB3's batched ``predict``; the planners score candidates for
the whole batch at once). Each episode depends only on its seed, so the result does not depend on
how many environments run side by side.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import pickle
import sys
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Final

import numpy as np

from agents.planners import PLANNERS, make_planner
from agents.stats import bootstrap_mean_ci, wilson_interval
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, load_yaml
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text, code_version
from envs.config import CrowdNavConfig, config_from

#: Outcomes of an episode, each reported as a rate with a Wilson interval.
OUTCOMES: Final[tuple[str, ...]] = ("success", "collision", "timeout")
#: Per-episode metrics averaged (with bootstrap intervals) in the summary.
METRICS: Final[tuple[str, ...]] = (
    "navigation_time_s",
    "path_length_m",
    "path_ratio",
    "min_gap_m",
    "discomfort_frequency",
    "intrusion_ratio",
    "mean_jerk_mps3",
    "forecast_ade_m",
    "forecast_fde_m",
    "crowd_density",
    "steps",
    "return",
)
#: Metrics averaged over successful episodes only (a collision cuts a trip short; a timeout has no arrival time).
SUCCESS_ONLY_METRICS: Final[tuple[str, ...]] = ("navigation_time_s", "path_length_m", "path_ratio")
#: Columns of ``episodes.csv``, in order (the metrics before ``steps`` and ``return``, then the collision details).
EPISODE_COLUMNS: Final[tuple[str, ...]] = (
    *("episode", "seed", "recording", "t0_s", "outcome"),
    *METRICS[:-2],
    *("pedestrians_near_path", "collisions", "collision_fault", "popin_events", "steps", "return"),
)
#: Names of the models a run folder holds, for ``which=``.
RUN_MODELS: Final[tuple[str, ...]] = ("best", "final")


class SB3Policy:
    """An SB3 model (and its ``VecNormalize`` statistics, if it was trained with them) behind ``predict``.

    Args:
        model: a loaded SB3 algorithm.
        vecnormalize: the ``VecNormalize`` whose observation statistics the model was trained with, or None.
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


# ---------------------------------------------------------------------------- loading policies


def algo_of_model(path: str | Path) -> str:
    """``"ppo"`` or ``"sac"``: which SB3 algorithm saved the ``.zip`` (from its policy class)."""
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.save_util import load_from_zip_file
    from stable_baselines3.sac.policies import SACPolicy

    data, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    policy_class = (data or {}).get("policy_class")
    if isinstance(policy_class, type) and issubclass(policy_class, SACPolicy):
        return "sac"
    if isinstance(policy_class, type) and issubclass(policy_class, ActorCriticPolicy):
        return "ppo"
    raise ValueError(f"{path}: not a PPO or SAC model saved by Stable-Baselines3 (policy class {policy_class!r})")


def load_sb3(path: str | Path, algo: str | None = None) -> SB3Policy:
    """Load an SB3 ``.zip`` (PPO or SAC, detected unless given) on the CPU, with ``<stem>_vecnormalize.pkl``
    beside it if present."""
    from stable_baselines3 import PPO, SAC

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no model file {path}")
    algo = algo or algo_of_model(path)
    cls = {"ppo": PPO, "sac": SAC}[algo]
    model = cls.load(path, device="cpu")
    vecnormalize = None
    stats = path.with_name(f"{path.stem}_vecnormalize.pkl")
    if stats.is_file():
        with open(stats, "rb") as fh:
            vecnormalize = pickle.load(fh)
        vecnormalize.training = False
        vecnormalize.norm_reward = False
    return SB3Policy(model, vecnormalize, str(path))


def config_of(spec: str | Path) -> Path | None:
    """The training config that goes with a policy spec: a run folder's ``config.yaml``, for a model file
    ``<stem>.yaml`` beside it (an exported policy, see :func:`export_policy`) or its folder's ``config.yaml``;
    None for planners and bare models."""
    p = Path(spec)
    if str(spec) in PLANNERS:
        return None
    if p.is_dir():
        return p / "config.yaml" if (p / "config.yaml").is_file() else None
    for candidate in (p.with_suffix(".yaml"), p.parent / "config.yaml"):
        if p.is_file() and candidate.is_file():
            return candidate
    return None


def run_settings(spec: str | Path) -> dict[str, Any]:
    """The project section (``algo``, ``env``, ``run``, ...) of the training config of a policy spec; empty when
    there is none (planners, bare models)."""
    from agents.train import PROJECT_KEY

    path = config_of(spec)
    if path is None:
        return {}
    section = load_yaml(path).get(PROJECT_KEY)
    if not isinstance(section, dict):
        raise ConfigError(f"{path} has no {PROJECT_KEY!r} section: not a config written by agents.train")
    return section


def export_policy(run_dir: str | Path, dest: str | Path, which: str = "best") -> Path:
    """Copy a run's model to ``dest`` (``.zip``) with its config as ``<stem>.yaml`` (and normalisation statistics
    as ``<stem>_vecnormalize.pkl``), so the file alone can be evaluated or shipped."""
    import shutil

    src = model_path(run_dir, which)
    dest = Path(dest)
    if dest.suffix != ".zip":
        raise ValueError(f"the exported policy must be a .zip path, got {dest}")
    config = config_of(src)
    if config is None:
        raise FileNotFoundError(f"{run_dir} holds no config.yaml: not a run folder of agents.train")
    atomic_write(dest, lambda fh: fh.write(without_optimizer_state(src.read_bytes())))
    atomic_write_text(dest.with_suffix(".yaml"), config.read_text())
    stats = src.with_name(f"{src.stem}_vecnormalize.pkl")
    if stats.is_file():
        shutil.copyfile(stats, dest.with_name(f"{dest.stem}_vecnormalize.pkl"))
    return dest


def without_optimizer_state(model_zip: bytes) -> bytes:
    """An SB3 model archive whose optimizer keeps its settings but not its moment estimates (Adam's are twice the
    policy's size and serve only to continue training); the policy, and so every action, is unchanged."""
    import io
    import zipfile

    import torch

    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(model_zip)) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.infolist():
            data = src.read(item.filename)
            if item.filename.endswith("optimizer.pth"):
                state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
                buf = io.BytesIO()
                torch.save({**state, "state": {}}, buf)
                data = buf.getvalue()
            dst.writestr(item, data)
    return out.getvalue()


def model_path(spec: str | Path, which: str = "best") -> Path:
    """The ``.zip`` a spec names: the spec itself, or ``best_model.zip``/``final_model.zip`` of a run folder
    (``best`` falls back to ``final`` when no validation ran)."""
    if which not in RUN_MODELS:
        raise ValueError(f"unknown model {which!r}; valid: {', '.join(RUN_MODELS)}")
    p = Path(spec)
    if p.is_file():
        return p
    if p.is_dir():
        for name in (f"{which}_model.zip", "final_model.zip"):
            if (p / name).is_file():
                return p / name
        raise FileNotFoundError(f"{p} holds neither {which}_model.zip nor final_model.zip (is the run finished?)")
    raise FileNotFoundError(
        f"no run folder, model file or planner named {str(spec)!r} (planners: {', '.join(PLANNERS)})"
    )


def load_policy(
    spec: str | Path,
    env_config: CrowdNavConfig | Mapping[str, Any] | None = None,
    which: str = "best",
    planner_kwargs: Mapping[str, Any] | None = None,
) -> Any:
    """A policy with SB3's ``predict``: ``"planner"``/``"straight"`` (built for ``env_config``, with
    ``planner_kwargs``), an SB3 ``.zip``, or a run folder (its best model, see :func:`model_path`)."""
    if str(spec) in PLANNERS:
        return make_planner(str(spec), env_config, **dict(planner_kwargs or {}))  # type: ignore[return-value]
    path = model_path(spec, which)
    settings = run_settings(path)
    policy: Any = load_sb3(path, settings.get("algo"))
    if (settings.get("action") or {}).get("kind", "continuous") != "continuous":
        from agents.actions import DiscretePolicy
        from agents.planners import as_env_config
        from agents.train import action_set

        policy = DiscretePolicy(policy, action_set(settings["action"], as_env_config(env_config)))
    return policy


def check_spaces(policy: Any, env: Any) -> None:
    """Raise ``ValueError`` if an SB3 policy was trained on another observation space than ``env`` gives."""
    space = getattr(policy, "observation_space", None)
    while space is None and hasattr(policy, "model"):  # adapters (e.g. discrete actions) around an SB3 policy
        policy = policy.model
        space = getattr(policy, "observation_space", None)
    if space is None:
        return
    want = {k: getattr(v, "shape", None) for k, v in space.spaces.items()}
    got = {k: getattr(v, "shape", None) for k, v in env.observation_space.spaces.items()}
    if want != got:
        raise ValueError(
            f"the policy was trained on observations {want} but the environment gives {got}: "
            "evaluate with the forecast arm and env settings it was trained with (forecasts vs none, "
            "observe_time_left, num_pedestrians, horizon_steps, kinematics)"
        )


# ---------------------------------------------------------------------------- running episodes


def prepare_forecasts(env_kwargs: Mapping[str, Any], progress: bool = False) -> dict[str, Any] | None:
    """Fill the shared on-disk forecast cache for the recordings environments of ``env_kwargs`` replay, so that no
    worker computes forecasts (:func:`envs.forecasting.build.build_forecast_cache`); None when there is nothing to build
    (no learned predictor, no disk cache, or a crowd that is not replayed from ETH/UCY).

    Raises:
        DataNotFoundError: the environments would replay ETH/UCY scenes and the data is not found (as they would).
    """
    import envs.forecasting.build as forecasts
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
            method (the privileged planner, :mod:`agents.privileged`) is given the environment of each row of the
            batch before each ``predict``.
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


# ---------------------------------------------------------------------------- aggregates


def _number(value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        return math.nan
    return x


def _json_float(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def summarise(rows: Sequence[Mapping[str, Any]], confidence: float = 0.95, seed: int = 0) -> dict[str, Any]:
    """Aggregates of per-episode rows.

    Returns:
        ``episodes``; for each outcome ``<outcome>_rate``, ``<outcome>_ci`` ([lo, hi], Wilson) and
        ``<outcome>_count`` (summaries written before this name held ``successs``, ``collisions`` and
        ``timeouts``; nothing in the project reads the counts back); ``popin_episodes`` (episodes with at least
        one pop-in event, see :mod:`envs.popin`) and ``popin_events`` (their total); for each of :data:`METRICS`
        ``<metric>_mean``, ``<metric>_ci``
        (bootstrap, seeded) and ``<metric>_n`` (episodes it is defined for: all, or the successful ones
        for :data:`SUCCESS_ONLY_METRICS`; ``None`` values such as the ``none`` arm's forecast ADE are
        left out). Undefined means and intervals are ``None``.
    """
    n = len(rows)
    out: dict[str, Any] = {"episodes": n}
    outcomes = [str(r.get("outcome")) for r in rows]
    for name in OUTCOMES:
        count = sum(o == name for o in outcomes)
        out[f"{name}_rate"] = count / n if n else None
        out[f"{name}_ci"] = list(wilson_interval(count, n, confidence)) if n else None
        out[f"{name}_count"] = count
    popins = np.array([_number(r.get("popin_events")) for r in rows], dtype=np.float64)
    out["popin_episodes"] = int(np.sum(popins > 0))  # episodes in which a track began on the robot (envs.popin)
    out["popin_events"] = int(np.nansum(popins)) if n else 0
    for metric in METRICS:
        use = [r for r in rows if metric not in SUCCESS_ONLY_METRICS or r.get("outcome") == "success"]
        values = np.array([_number(r.get(metric)) for r in use], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[f"{metric}_n"] = len(values)
        out[f"{metric}_mean"] = float(values.mean()) if len(values) else None
        lo, hi = bootstrap_mean_ci(values, confidence=confidence, seed=seed) if len(values) else (math.nan, math.nan)
        out[f"{metric}_ci"] = [_json_float(lo), _json_float(hi)] if len(values) else None
    return out


def read_episodes(path: str | Path) -> list[dict[str, Any]]:
    """The rows of an ``episodes.csv`` (``path`` is the file or an evaluation folder holding it), as strings."""
    p = Path(path)
    if p.is_dir():
        p = p / "episodes.csv"
    if not p.is_file():
        raise FileNotFoundError(f"no episodes.csv at {path} (give the file or an evaluation folder with --out)")
    with open(p, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for key in ("seed", "outcome"):
        if rows and key not in rows[0]:
            raise ValueError(f"{p}: no {key!r} column; not an episodes.csv of agents.evaluate")
    return rows


def ceiling_fraction(
    rows: Sequence[Mapping[str, Any]],
    ceiling_rows: Sequence[Mapping[str, Any]],
    confidence: float = 0.95,
    seed: int = 0,
    n_resamples: int = 2000,
) -> dict[str, Any]:
    """A policy's success as a fraction of the privileged ceiling's (:mod:`agents.privileged`) on the same episodes.

    Episodes are paired by seed (rows of the same evaluation list); a pair whose recording or start time differ
    is an error (the two evaluations ran different environment settings).

    Args:
        rows: the policy's episodes (``seed``, ``outcome``; ``recording``, ``t0_s`` checked when both have them).
        ceiling_rows: the ceiling's episodes.
        confidence: level of the interval.
        seed: seed of the bootstrap.
        n_resamples: bootstrap resamples.

    Returns:
        ``episodes`` (pairs), ``success_rate`` and ``ceiling_success_rate`` on them, ``fraction`` (their ratio;
        None when the ceiling never succeeds), ``fraction_ci`` (paired bootstrap over episodes, percentile, from
        ``scipy.stats.bootstrap``), and ``success_where_ceiling_succeeds`` (the policy's success rate on the
        episodes the ceiling solves).
    """
    from scipy import stats

    ceiling = {int(r["seed"]): r for r in ceiling_rows}
    mine, theirs = [], []
    for r in rows:
        other = ceiling.get(int(r["seed"]))
        if other is None:
            continue
        for key in ("recording", "t0_s"):
            a, b = r.get(key), other.get(key)
            if a not in (None, "") and b not in (None, "") and str(a) != str(b) and _number(a) != _number(b):
                raise ValueError(
                    f"episode seed {r['seed']}: {key} {a!r} here but {b!r} in the ceiling's episodes; the two "
                    "evaluations ran different episodes (split, require_pedestrians or env settings differ)"
                )
        mine.append(r.get("outcome") == "success")
        theirs.append(other.get("outcome") == "success")
    n = len(mine)
    a, c = np.array(mine, dtype=np.float64), np.array(theirs, dtype=np.float64)
    out: dict[str, Any] = {"episodes": n, "success_rate": None, "ceiling_success_rate": None, "fraction": None}
    out.update(fraction_ci=None, success_where_ceiling_succeeds=None)
    if n == 0:
        return out
    out["success_rate"], out["ceiling_success_rate"] = float(a.mean()), float(c.mean())
    if c.any():
        out["fraction"] = float(a.mean() / c.mean())
        out["success_where_ceiling_succeeds"] = float(a[c > 0].mean())

        def ratio(x: np.ndarray, y: np.ndarray, axis: int = -1) -> np.ndarray:
            den = y.mean(axis=axis)
            return np.divide(x.mean(axis=axis), den, out=np.full(np.shape(den), np.nan), where=den > 0)

        if np.all(a == a[0]) and np.all(c == c[0]):
            out["fraction_ci"] = [out["fraction"], out["fraction"]]
        else:
            res = stats.bootstrap(
                (a, c), ratio, paired=True, vectorized=True, method="percentile", n_resamples=n_resamples,
                confidence_level=confidence, rng=np.random.default_rng(seed),
            )  # fmt: skip
            out["fraction_ci"] = [_json_float(res.confidence_interval.low), _json_float(res.confidence_interval.high)]
    return out


def episodes_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """``episodes.csv`` text (columns :data:`EPISODE_COLUMNS`; empty cells where a metric is undefined)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(EPISODE_COLUMNS), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in EPISODE_COLUMNS})
    return buf.getvalue()


# ---------------------------------------------------------------------------- evaluate


def evaluation_env_kwargs(
    spec: str | Path,
    predictor: str,
    split: str,
    env_overrides: Mapping[str, Any] | None = None,
    require_pedestrians: bool = True,
) -> dict[str, Any]:
    """Keyword arguments of the evaluation environments: the policy's own env settings (see :func:`config_of`),
    then ``env_overrides``, on the split's held-out scene over its whole duration."""
    kwargs = {**dict(run_settings(spec).get("env") or {}), **dict(env_overrides or {})}
    kwargs.update(predictor=predictor, split=split, part="test", episode_time="all")
    kwargs["require_pedestrians"] = dict(env_overrides or {}).get("require_pedestrians", require_pedestrians)
    return kwargs


def evaluate(
    spec: str | Path,
    predictor: str,
    split: str,
    episodes: int,
    seed: int = 0,
    out_dir: str | Path | None = None,
    env_overrides: Mapping[str, Any] | None = None,
    require_pedestrians: bool = True,
    n_envs: int = 4,
    which: str = "best",
    progress: bool = False,
    planner_kwargs: Mapping[str, Any] | None = None,
    ceiling: str | Path | None = None,
) -> dict[str, Any]:
    """Evaluate a policy on the held-out scene of ``split`` over :func:`evaluation_seeds`.

    Args:
        spec: a planner name (:data:`agents.planners.PLANNERS`: ``straight``, ``planner``, ``search``,
            ``privileged``), an SB3 ``.zip``, or a run folder of :mod:`agents.train`.
        predictor: the forecast arm of the environment.
        split: whose held-out scene is replayed.
        episodes: how many episodes.
        seed: which seeded list of episodes (0 = the reported one).
        out_dir: where to write ``episodes.csv`` and ``summary.json`` (atomically), or None.
        env_overrides: environment settings on top of the run's own.
        require_pedestrians: keep only episodes in which a pedestrian comes near the straight path.
        n_envs: environments stepped in lockstep (only speed changes).
        which: ``best`` or ``final`` model of a run folder.
        progress: show a progress bar.
        planner_kwargs: options of the planner (e.g. the sampling planner's ``candidates``, ``headings_deg``,
            ``speed_fractions``, ``margin_m``, ``lookahead_steps``; see :mod:`agents.planners`).
        ceiling: the privileged ceiling's ``episodes.csv`` (or its evaluation folder) on the same episode list: the
            summary then holds ``ceiling`` (:func:`ceiling_fraction`).

    Returns:
        the summary (see :func:`summarise`) plus ``policy``, ``predictor``, ``split``, ``crowd`` (``{"kind",
        "data_dir"}``: ``replay`` from that ETH/UCY folder, or ``synthetic``/``empty``), ``seed``,
        ``require_pedestrians``, ``env`` (the settings given to the environments), ``privileged`` (the policy
        reads the replay's true future: :mod:`agents.privileged`), ``env_revision`` (the environment's rules,
        :data:`envs.crowd_nav.ENV_REVISION`), ``code_version``, ``seconds`` and ``out_dir``.
    """
    from envs.crowd_nav import ENV_REVISION, CrowdNavEnv

    predictors.check(predictor)
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs!r}")
    started = time.perf_counter()
    version = code_version()  # the code that runs (read before: the checkout may move while episodes run)
    ceiling_rows = read_episodes(ceiling) if ceiling is not None else None  # fail before running anything
    kwargs = evaluation_env_kwargs(spec, predictor, split, env_overrides, require_pedestrians)
    config = config_from(kwargs, {})
    policy = load_policy(spec, config, which, planner_kwargs)
    prepare_forecasts(kwargs, progress=progress)
    envs = [CrowdNavEnv(**kwargs) for _ in range(max(1, min(n_envs, episodes)))]
    check_spaces(policy, envs[0])
    try:
        rows = run_episodes(
            policy, envs, evaluation_seeds(split, episodes, seed), progress=progress, desc=f"evaluation on {split}"
        )
    finally:
        for env in envs:
            env.close()
    summary = summarise(rows)
    summary.update(
        policy=str(spec),
        model=None if str(spec) in PLANNERS else str(model_path(spec, which)),
        predictor=predictor,
        split=split,
        crowd=envs[0].crowd_source.as_dict(),
        seed=seed,
        require_pedestrians=kwargs["require_pedestrians"],
        env=kwargs,
        planner=dict(planner_kwargs or {}) if str(spec) in PLANNERS else None,
        privileged=bool(getattr(policy, "privileged", False)),
        env_revision=ENV_REVISION,
        code_version=version,
        seconds=round(time.perf_counter() - started, 3),
        out_dir=None if out_dir is None else str(out_dir),
    )
    if ceiling_rows is not None:
        summary["ceiling"] = {"source": str(ceiling), **ceiling_fraction(rows, ceiling_rows)}
    if out_dir is not None:
        out = Path(out_dir)
        atomic_write_text(out / "episodes.csv", episodes_csv(rows))
        atomic_write_json(out / "summary.json", summary)
    return summary


def default_eval_dir(spec: str | Path, predictor: str, split: str, seed: int, root: str | Path = "runs/eval") -> Path:
    """A new folder for an evaluation's files when none is given: ``runs/eval/<policy>_<predictor>_<split>_s<seed>_<UTC
    time>`` (``<policy>``: the planner's name, a run folder's name or a model file's stem; ``-2``, ``-3``, ... appended
    when the folder exists, so an evaluation never overwrites another)."""
    p = Path(spec)
    name = str(spec) if str(spec) in PLANNERS else (p.stem if p.suffix == ".zip" else p.name) or "policy"
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    base = Path(root) / f"{name}_{predictor}_{split}_s{seed}_{stamp}"
    out, k = base, 1
    while out.exists():
        k += 1
        out = base.with_name(f"{base.name}-{k}")
    return out


def format_summary(summary: Mapping[str, Any]) -> str:
    """A short human-readable table of a summary."""

    def ci(key: str) -> str:
        value = summary.get(key)
        return "" if not value or value[0] is None else f"  [{value[0]:.3f}, {value[1]:.3f}]"

    rows = [(f"{name} rate", summary.get(f"{name}_rate"), f"{name}_ci") for name in OUTCOMES]
    rows += [
        (
            metric + (" (successes)" if metric in SUCCESS_ONLY_METRICS else ""),
            summary.get(f"{metric}_mean"),
            f"{metric}_ci",
        )
        for metric in METRICS
    ]
    width = max(len(label) for label, _, _ in rows) + 2
    crowd = summary.get("crowd") or {}
    if crowd.get("kind") == "replay":
        where = f"{summary.get('split')} (held-out scene, ETH/UCY replay from {crowd.get('data_dir')})"
    elif crowd:
        where = f"the {crowd.get('kind')} crowd (not an ETH/UCY scene; split {summary.get('split')})"
    else:  # a summary written before crowds were named
        where = f"{summary.get('split')} (held-out scene)"
    lines = [
        f"{summary.get('policy')} on {where}, forecasts {summary.get('predictor')}, "
        f"{summary['episodes']} episodes in {summary.get('seconds', 0):.1f} s"
    ]
    if summary.get("privileged"):
        lines.append("  PRIVILEGED: reads every pedestrian's true future from the replay (a ceiling, not a policy)")
    for label, value, ci_key in rows:
        lines.append(f"  {label:<{width}}{'-' if value is None else f'{value:.3f}'}{ci(ci_key)}")
        if label == f"{OUTCOMES[-1]} rate":
            ceiling = summary.get("ceiling")
            if ceiling and ceiling.get("fraction") is not None:
                lo, hi = ceiling["fraction_ci"]
                lines.append(
                    f"  {'success / ceiling':<{width}}{ceiling['fraction']:.3f}  [{lo:.3f}, {hi:.3f}]  (ceiling "
                    f"{ceiling['ceiling_success_rate']:.3f} on {ceiling['episodes']} paired episodes)"
                )
    return "\n".join(lines)


# ---------------------------------------------------------------------------- command line


def parse_set(items: Sequence[str] | None) -> dict[str, Any]:
    """``["key=value", ...]`` to a dict, values read as YAML (``1e-4``, ``true``, ``[64, 64]``, ``null``)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects key=value, got {item!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "policy",
        help="a run folder of agents.train, an SB3 .zip, or a planner: 'straight', 'planner' (sampling), 'search', "
        "'privileged' (PRIVILEGED ceiling: reads the replay's true future)",
    )
    p.add_argument(
        "--predictor",
        default="mesrnn",
        metavar="PREDICTOR",
        help=f"forecast arm: {', '.join(predictors.names(plugins=False))}, an installed predictor plug-in or an "
        "import path package.module:Factory (default: mesrnn)",
    )
    p.add_argument("--split", default="zara1", choices=SPLITS, help="its held-out scene is replayed (default: zara1)")
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--episodes", type=int, default=500, help="number of episodes (default: 500)")
    p.add_argument("--seed", type=int, default=0, help="which seeded list of episodes (default: 0)")
    p.add_argument(
        "--out",
        default=None,
        help="folder for episodes.csv and summary.json (default: a new runs/eval/<policy>_<predictor>_<split>_s<seed>_<time>)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument(
        "--all-episodes",
        action="store_true",
        help="keep episodes in which no pedestrian comes near the path (default: require one)",
    )
    p.add_argument("--model", default="best", choices=RUN_MODELS, help="model of a run folder (default: best)")
    p.add_argument(
        "--planner-set",
        dest="planner_set",
        action="append",
        metavar="KEY=VALUE",
        help="planner option, e.g. candidates=dense (sampling planner), lookahead_steps=8 (search), "
        "max_states=3000 (privileged)",
    )
    p.add_argument(
        "--ceiling",
        default=None,
        metavar="PATH",
        help="the privileged ceiling's episodes.csv (or --out folder) on the same episodes: report success / ceiling",
    )
    p.add_argument("--n-envs", type=int, default=4, help="environments stepped in lockstep (default: 4)")
    p.add_argument("--set", dest="env_set", action="append", metavar="KEY=VALUE", help="environment setting override")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_from_args(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(1)
    out = Path(args.out) if args.out else default_eval_dir(args.policy, args.predictor, args.split, args.seed)
    summary = evaluate(
        args.policy,
        args.predictor,
        args.split,
        args.episodes,
        seed=args.seed,
        out_dir=out,
        env_overrides=parse_set(args.env_set),
        require_pedestrians=not args.all_episodes,
        n_envs=args.n_envs,
        which=args.model,
        planner_kwargs=parse_set(args.planner_set),
        ceiling=args.ceiling,
        progress=not (args.no_progress or args.json),
    )
    if args.json:
        print(json.dumps(summary))
    else:
        print(format_summary(summary))
        print(f"wrote {out / 'episodes.csv'} and {out / 'summary.json'}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from agents.entry import module_main

    return module_main("python -m agents.evaluate", __doc__, add_evaluate_arguments, run_from_args, argv)


if __name__ == "__main__":
    sys.exit(main())
