""":func:`run_policy_bench`: a user's policy on the held-out scenes' fixed episode lists with each forecast arm,
against the shipped planners and the privileged ceiling on the same episodes, with paired tests; one report."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Final

from agents.policy_bench.references import REFERENCES, reference_arms

#: Default forecast arms.
DEFAULT_ARMS: Final[tuple[str, ...]] = ("none", "cv", "mesrnn", "oracle")
#: Default episodes per scene (the planner grid has 500: the first ``n`` of its lists are a bench's).
DEFAULT_EPISODES: Final[int] = 100
#: Family-wise error rate of the verdicts.
ALPHA: Final[float] = 0.05
#: Metrics the report tabulates besides the outcome rates (means over episodes, see docs/env.md).
REPORT_METRICS: Final[tuple[str, ...]] = (
    "spl",
    "path_ratio_required",
    "navigation_time_s",
    "min_clearance_m",
    "min_ttc_s",
    "discomfort_frequency",
    "mean_jerk_mps3",
)


@dataclass(frozen=True)
class PolicyBenchConfig:
    """What one policy bench runs."""

    policy: str
    """Import path ``package.module:attr`` of the policy (see :mod:`agents.policy_bench.policy`)."""
    splits: tuple[str, ...] = ("eth", "hotel", "univ", "zara1", "zara2")
    """Leave-one-out splits whose held-out scenes are crossed."""
    arms: tuple[str, ...] = DEFAULT_ARMS
    """Forecast arms the policy runs with (each against the references in the same arm)."""
    episodes: int = DEFAULT_EPISODES
    """Episodes per scene and arm: the first ``episodes`` of the scene's fixed list."""
    seed: int = 0
    """Which fixed list (0: the one every grid reports)."""
    env: Mapping[str, Any] = field(default_factory=dict)
    """Environment overrides, alike for the policy and the references (non-empty: references run here)."""
    rerun_references: bool = False
    """Run the references here even when the committed planner grid holds the episodes."""
    n_envs: int = 4
    """Environments stepped in lockstep (only speed changes)."""


def env_kwargs(arm: str, split: str, env: Mapping[str, Any]) -> dict[str, Any]:
    """The environment an evaluation of a planner runs (:func:`agents.evaluation.evaluation_env_kwargs` without a
    run's own settings): the held-out scene over its whole duration, episodes with a pedestrian near the path."""
    kwargs = dict(env)
    kwargs.update(predictor=arm, split=split, part="test", episode_time="all")
    kwargs["require_pedestrians"] = dict(env).get("require_pedestrians", True)
    return kwargs


def run_policy(
    cfg: PolicyBenchConfig, arm: str, split: str, progress: bool = False
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The policy's episodes with forecast arm ``arm`` on ``split``'s held-out scene, and what it was."""
    from agents.policy_bench.policy import UserPolicy
    from agents.rollout import evaluation_seeds, prepare_forecasts, run_episodes
    from envs.config import config_from
    from envs.crowd_nav import CrowdNavEnv

    kwargs = env_kwargs(arm, split, cfg.env)
    policy = UserPolicy(cfg.policy, config_from(kwargs, {}))
    prepare_forecasts(kwargs, progress=progress)
    envs = [CrowdNavEnv(**kwargs) for _ in range(max(1, min(cfg.n_envs, cfg.episodes)))]
    try:
        rows = run_episodes(
            policy,
            envs,
            evaluation_seeds(split, cfg.episodes, cfg.seed),
            progress=progress,
            desc=f"{cfg.policy} on {split}, {arm}",
        )
        crowd = envs[0].crowd_source.as_dict()
    finally:
        for env in envs:
            env.close()
    return rows, {"kind": policy.kind, "factory": policy.factory, "crowd": crowd}


def _cell(rows: Sequence[Mapping[str, Any]], source: str | None = None) -> dict[str, Any]:
    """Rates with Wilson intervals and the report's metric means with bootstrap intervals (absent: not recorded)."""
    from agents.evaluation import summarise

    s = summarise(rows)
    keep = ["episodes"] + [f"{o}_{x}" for o in ("success", "collision", "timeout") for x in ("rate", "ci", "count")]
    keep += [f"{m}_{x}" for m in REPORT_METRICS for x in ("mean", "ci", "n") if f"{m}_mean" in s]
    return {**({"source": source} if source else {}), **{k: s[k] for k in keep}}


def _successes(rows: Sequence[Mapping[str, Any]]) -> list[bool]:
    return [str(r.get("outcome")) == "success" for r in rows]


def run_policy_bench(
    cfg: PolicyBenchConfig,
    out_dir: str | Path,
    *,
    command: str = "",
    progress: bool = False,
    log: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Run a policy bench and write ``report.md``, ``report.json`` and ``success_by_scene.png`` into ``out_dir``
    (the policy's episodes under ``policy/<split>/<arm>/``, references run here under ``references/``).

    Returns:
        the report: ``policy``, ``config``, ``command``, ``code_version``, ``env_revision``, ``policy_kind``
        (``predict`` or ``callable``), ``scenes`` (``{split: {"policy": {arm: cell}, "references": {name: {arm:
        cell}}}}``, a cell being rates with Wilson intervals and metric means with bootstrap intervals, and for a
        reference its ``source``: ``committed``, ``cached`` or ``run``), ``tests`` (exact McNemar of the policy
        against each reference per scene and arm, same episodes, Holm-adjusted over all, each with
        ``difference_exact_ci`` and ``verdict``), ``alpha``, ``seconds``.
    """
    from agents.evaluation import episodes_csv
    from agents.policy_bench.references import committed_grid, reference_rows
    from agents.policy_bench.report import write_report
    from agents.stats import holm, mcnemar_exact, paired_verdict
    from crowdnav_mesrnn.utils import atomic_write_text, code_version
    from envs.crowd_nav import ENV_REVISION
    from envs.reaction import revision_rules

    started = time.perf_counter()
    out = Path(out_dir)
    version = code_version()
    grid = committed_grid() if not cfg.rerun_references else (None, {})
    scenes: dict[str, Any] = {}
    tests: list[dict[str, Any]] = []
    kind = None
    for split in cfg.splits:
        scene: dict[str, Any] = {"policy": {}, "references": {name: {} for name in REFERENCES}}
        success: dict[tuple[str, str], list[bool]] = {}
        for arm in cfg.arms:
            log(f"{cfg.policy} on {split}, arm {arm}: {cfg.episodes} episodes")
            rows, meta = run_policy(cfg, arm, split, progress)
            kind = meta["kind"]
            atomic_write_text(out / "policy" / split / arm / "episodes.csv", episodes_csv(rows))
            scene["policy"][arm] = _cell(rows)
            scene["crowd"] = meta["crowd"]
            success[("policy", arm)] = _successes(rows)
            for name in REFERENCES:
                for ref_arm in reference_arms(name, [arm]):
                    if ref_arm in scene["references"][name]:
                        continue  # the ceiling: one arm for every arm of the policy
                    ref_rows, source = reference_rows(
                        name, ref_arm, split, cfg.episodes, cfg.seed, cfg.env, rows, out / "references", grid,
                        cfg.rerun_references, progress, log,
                    )  # fmt: skip
                    scene["references"][name][ref_arm] = _cell(ref_rows, source)
                    success[(name, ref_arm)] = _successes(ref_rows)
        for arm in cfg.arms:
            for name in REFERENCES:
                ref_arm = (reference_arms(name, [arm]) or [None])[0]
                if ref_arm is None:
                    continue
                t = mcnemar_exact(success[("policy", arm)], success[(name, ref_arm)])
                tests.append({"scene": split, "arm": arm, "reference": name, "reference_arm": ref_arm, **t})
        scenes[split] = scene
    for t, adj in zip(tests, holm([t["p_value"] for t in tests]) if tests else [], strict=True):
        t["p_holm"] = adj
        t["verdict"] = paired_verdict(t["difference"], adj, ALPHA)
    report: dict[str, Any] = {
        "policy": cfg.policy,
        "policy_kind": kind,
        "config": {**asdict(cfg), "env": dict(cfg.env)},
        "command": command or f"crowdnav-mesrnn bench-policy {cfg.policy}",
        "code_version": version,
        "env_revision": ENV_REVISION,
        **revision_rules(dict(cfg.env).get("reaction", "none")),
        "grid": str(grid[0].source) if grid[0] is not None else None,
        "scenes": scenes,
        "tests": tests,
        "alpha": ALPHA,
        "seconds": round(time.perf_counter() - started, 1),
    }
    write_report(report, out)
    return report
