""":func:`evaluate`: a policy on the held-out scene of a split over the fixed episode list, its files written."""

from __future__ import annotations

import time
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from agents.evaluation import episode_part
from agents.evaluation.summary import ceiling_fraction, episodes_csv, read_episodes, summarise
from agents.planners import PLANNERS
from agents.policy_file import POLICY_SUFFIX
from agents.rollout import evaluation_seeds, prepare_forecasts, run_episodes
from agents.runs import check_spaces, load_policy, model_path, run_settings
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text, code_version
from envs.config import config_from


def evaluation_env_kwargs(
    spec: str | Path,
    predictor: str,
    split: str,
    env_overrides: Mapping[str, Any] | None = None,
    require_pedestrians: bool = True,
    episodes_from: str = "test",
) -> dict[str, Any]:
    """Keyword arguments of the evaluation environments: the policy's own env settings (see :func:`config_of`),
    then ``env_overrides``, on the split's held-out scene over its whole duration (``episodes_from="test"``) or on its
    training scenes' validation period (``"val"``; :data:`agents.evaluation.EPISODE_SOURCES`)."""
    kwargs = {**dict(run_settings(spec).get("env") or {}), **dict(env_overrides or {})}
    kwargs.update(predictor=predictor, split=split, **episode_part(episodes_from))
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
    trust_pickle: bool = False,
    episodes_from: str = "test",
) -> dict[str, Any]:
    """Evaluate a policy on the held-out scene of ``split`` (or its training scenes' validation period) over
    :func:`evaluation_seeds`.

    Args:
        spec: a planner name (:data:`agents.planners.PLANNERS`: ``straight``, ``planner``, ``search``,
            ``privileged``), a policy file (``NAME.policy.yaml``), a run folder of :mod:`agents.training`, or an SB3
            ``.zip`` (with ``trust_pickle``).
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
        trust_pickle: allow an SB3 ``.zip`` (and its ``_vecnormalize.pkl``), which is unpickled and can run arbitrary
            code (:func:`agents.runs.load_policy`).
        episodes_from: ``test`` (the held-out scene over its whole duration) or ``val`` (the split's training scenes
            in their validation period, ``part="train"``, ``episode_time="val"``: for choices, never a held-out
            result); :data:`agents.evaluation.EPISODE_SOURCES`.

    Returns:
        the summary (see :func:`summarise`) plus ``policy``, ``predictor``, ``split``, ``crowd`` (``{"kind",
        "data_dir"}``: ``replay`` from that ETH/UCY folder, or ``synthetic``/``empty``), ``seed``,
        ``require_pedestrians``, ``env`` (the settings given to the environments), ``privileged`` (the policy
        reads the replay's true future: :mod:`agents.planners.privileged`), ``env_revision`` (the environment's rules,
        :data:`envs.crowd_nav.ENV_REVISION`), ``code_version``, ``seconds`` and ``out_dir``.
    """
    from envs.crowd_nav import ENV_REVISION, CrowdNavEnv
    from envs.reaction import revision_rules

    predictors.check(predictor)
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs!r}")
    started = time.perf_counter()
    version = code_version()  # the code that runs (read before: the checkout may move while episodes run)
    ceiling_rows = read_episodes(ceiling) if ceiling is not None else None  # fail before running anything
    kwargs = evaluation_env_kwargs(spec, predictor, split, env_overrides, require_pedestrians, episodes_from)
    config = config_from(kwargs, {})
    policy = load_policy(spec, config, which, planner_kwargs, trust_pickle=trust_pickle)
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
        **revision_rules(config.reaction),
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
    time>`` (``<policy>``: the planner's name, a run folder's name or a model file's ``NAME``; ``-2``, ``-3``, ... appended
    when the folder exists, so an evaluation never overwrites another)."""
    p = Path(spec)
    name = str(spec) if str(spec) in PLANNERS else p.name.removesuffix(POLICY_SUFFIX).removesuffix(".zip") or "policy"
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    base = Path(root) / f"{name}_{predictor}_{split}_s{seed}_{stamp}"
    out, k = base, 1
    while out.exists():
        k += 1
        out = base.with_name(f"{base.name}-{k}")
    return out
