""":func:`summarize`: finished evaluation cells into summary.json, summary.md, cells.json, the episode archive
(``episodes/``, one file per policy), plots.

The cells come from the run folders, or from the committed results for cells without a folder (the grid's own, then
the other grids' its config lists under ``reuse``); what may be replaced, and when files are left alone, is
:mod:`agents.ablation.results`' rule.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agents.ablation.archive import ARCHIVE_DIR, archive_path, files_rows, stored_as, write_archive
from agents.ablation.cells import _now
from agents.ablation.config import AblationConfig
from agents.ablation.episodes import (
    _Episodes,
    aggregate,
    cell_info,
    episode_intervals,
    episodes_archive,
    read_archive,
)
from agents.ablation.plots import write_plots
from agents.ablation.report import summary_markdown
from agents.ablation.results import CELLS, STAMPS, _load_json, _strip, check_replace, gather
from agents.ablation.stats import (
    _clean,
    by_density,
    density_edges,
    disturbance_summary,
    disturbance_tests,
    paired_tests,
    reaction_tests,
)
from agents.evaluation import EPISODE_SOURCES
from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text, code_version


def ceiling_fractions(cfg: AblationConfig, policies: dict[str, Any], which: int = 0) -> dict[str, Any] | None:
    """Every policy's success per arm and split as a fraction of the privileged ceiling's on the same episodes
    (``None`` when the grid has no ``privileged`` policy). The ceiling is a measuring stick: it reads the replay's
    true future (with the option ``reactive: true``, the reaction model rolled forward for its candidate plans), which
    no other policy's observation carries; it runs one arm (its forecast input is unused). ``which``: the grid's
    ``which``-th privileged policy; only the policies in the same environment as it (the same reaction,
    :meth:`AblationConfig.env_for`) are divided by it.

    Returns ``{"policy": NAME, "by_split": {split: rate}, "fractions": {policy: {arm: {split: fraction}}}}``, plus
    ``"reactive": true`` for the reactive ceiling.
    """
    from agents.ablation.config import PRIVILEGED_KIND

    names = [p.name for p in cfg.policies if p.kind == PRIVILEGED_KIND]
    if len(names) <= which or not policies.get(names[which], {}).get("arms"):
        return None
    ceiling_arm = next(iter(policies[names[which]]["arms"].values()))
    rates = {sp: e["success_rate"] for sp, e in ceiling_arm["by_split"].items()}
    env = cfg.env_for(cfg.policy(names[which]))
    fractions: dict[str, Any] = {}
    for name, pol in policies.items():
        if name == names[which] or cfg.env_for(cfg.policy(name)) != env:
            continue
        fractions[name] = {
            arm: {
                sp: (e["success_rate"] / rates[sp] if rates.get(sp) else None)
                for sp, e in entry["by_split"].items()
                if sp in rates
            }
            for arm, entry in pol["arms"].items()
        }
    out = {"policy": names[which], "by_split": rates, "fractions": fractions}
    if cfg.policy(names[which]).options.get("reactive"):
        out["reactive"] = True
    return out


def avoidable_failures(cfg: AblationConfig, pooled: dict[tuple[str, str], _Episodes]) -> list[dict[str, Any]]:
    """Each policy's failures classed by the privileged ceiling of its environment (the same reaction): a failure in
    an episode the ceiling succeeded in was **avoidable** (under this model of reaction: the ceiling's success proves
    a clear way existed); one the ceiling failed too is **not shown avoidable** (the ceiling's beam search is not
    complete, so this does not prove it unavoidable). Episodes are matched by split and episode index (the same
    seeded list; a learned policy's seeds each against the ceiling's one episode).

    Returns one entry per ceiling: ``{"policy": CEILING, "ceiling_failures": {split: n}, "classes": {policy: {arm:
    {"failures", "avoidable", "not_shown_avoidable", "unmatched", "by_split": {split: {...}}}}}}``; a failure in an
    episode with no ceiling episode of that index is counted in ``unmatched``.
    """
    from agents.ablation.config import PRIVILEGED_KIND

    out: list[dict[str, Any]] = []
    for ceiling in (p for p in cfg.policies if p.kind == PRIVILEGED_KIND):
        ceps = next((e for (name, _), e in pooled.items() if name == ceiling.name), None)
        if ceps is None:
            continue
        won = {(k[0], k[2]): o == "success" for k, o in zip(ceps.keys, ceps.outcome(), strict=True)}
        env = cfg.env_for(ceiling)
        classes: dict[str, Any] = {}
        for policy in cfg.policies:
            if policy.kind == PRIVILEGED_KIND or cfg.env_for(policy) != env:
                continue
            for arm in cfg.arm_labels:
                eps = pooled.get((policy.name, arm))
                if eps is None:
                    continue
                by_split: dict[str, dict[str, int]] = {}
                for key, outcome in zip(eps.keys, eps.outcome(), strict=True):
                    row = by_split.setdefault(
                        key[0], {"failures": 0, "avoidable": 0, "not_shown_avoidable": 0, "unmatched": 0}
                    )
                    if outcome == "success":
                        continue
                    row["failures"] += 1
                    ceiling_won = won.get((key[0], key[2]))
                    row[
                        "unmatched" if ceiling_won is None else "avoidable" if ceiling_won else "not_shown_avoidable"
                    ] += 1
                total = {
                    k: sum(r[k] for r in by_split.values())
                    for k in ("failures", "avoidable", "not_shown_avoidable", "unmatched")
                }
                classes.setdefault(policy.name, {})[arm] = {
                    **total,
                    "by_split": dict(sorted(by_split.items(), key=lambda kv: cfg.splits.index(kv[0]))),
                }
        fails: dict[str, int] = {}
        for key, ok in won.items():
            fails[key[0]] = fails.get(key[0], 0) + (not ok)
        out.append({"policy": ceiling.name, "ceiling_failures": fails, "classes": classes})
    return out


def summarize(
    cfg: AblationConfig, out: Callable[[str], None] = print, plots: bool = True, force: bool = False
) -> dict[str, Any]:
    """Write ``summary.json``, ``summary.md``, ``cells.json``, the episode archive (``episodes/``, one file per
    policy: :mod:`agents.ablation.archive`) and the plots into ``cfg.out_path()``; returns the summary.

    The statistics are computed from the episode archive as written (so the committed results alone render
    the same summary again). Every file is rendered before any is replaced; when only the stamps (code
    version, time) would change, nothing is written, and when only the archive's layout would (the older single
    ``episodes.csv.gz``, the same rows), only the archive is. An older ``episodes.csv.gz`` is removed when the new archive
    holds every one of its rows, else left with a warning (:func:`agents.ablation.archive.write_archive`). Raises
    :class:`agents.ablation.results.ResultsKept` (files untouched) when the new summary would hold less than the
    existing one, or -- drawn from the committed archive alone -- differ from it; ``force`` replaces them anyway.
    """
    records, episodes, sources = gather(cfg)
    raw: dict[tuple[str, str], _Episodes] = {}
    for policy_name, arm_label, split, seed, rows in episodes:
        raw.setdefault((policy_name, arm_label), _Episodes()).add(split, seed, rows)
    archive = episodes_archive(raw)
    rows = files_rows(archive)
    pooled = read_archive(rows, cfg.splits)
    info = cell_info(records)
    edges = density_edges(cfg, pooled)
    policies: dict[str, Any] = {}
    for policy in cfg.policies:
        arms: dict[str, Any] = {}
        for arm in cfg.arms:
            eps = pooled.get((policy.name, arm.label))
            if eps is None:
                continue
            # a seeded policy under test_unit: episode resamples episodes (with all their seeds) for its intervals
            by_episode = cfg.test_unit == "episode" and any(s is not None for _, s, _ in eps.keys)

            def rates(sub: _Episodes, by_episode: bool = by_episode) -> dict[str, Any]:
                out = aggregate(sub)
                return episode_intervals(sub, out) if by_episode else out

            entry: dict[str, Any] = {
                "predictor": arm.predictor,
                "noisy_oracle_ade_m": arm.noisy_oracle_ade_m,
                **arm.spec(),  # absent in point arms: their summaries stay
                "seeds": sorted({s for _, s, _ in eps.keys if s is not None}),
                "splits": sorted({sp for sp, _, _ in eps.keys}),
                **rates(eps),
                **disturbance_summary(eps),  # nothing for episodes without them (grids before reacting pedestrians)
            }
            entry["by_split"] = {
                split: {**rates(sub), **disturbance_summary(sub)}
                for split in entry["splits"]
                for sub in [eps.subset([k[0] == split for k in eps.keys])]
            }
            entry["by_density"] = by_density(eps, edges, by_episode=by_episode)
            arms[arm.label] = entry
        policies[policy.name] = {
            "kind": policy.kind,
            "timesteps": policy.timesteps,
            "n_envs": policy.n_envs if policy.learned else None,
            "model": policy.model if policy.learned else None,
            "agent_config": policy.config,
            # a policy in its own environment (a reaction): which, with every parameter; absent in other grids
            **({"reaction": cfg.reaction(policy), "env": cfg.env_for(policy)} if policy.env else {}),
            "arms": arms,
        }
    ceiling = ceiling_fractions(cfg, policies)
    privileged = sum(p.kind == "privileged" for p in cfg.policies)
    ceilings = [c for i in range(privileged) if (c := ceiling_fractions(cfg, policies, i))] if privileged > 1 else []
    tests, families = paired_tests(cfg, pooled)
    extra: dict[str, Any] = {}  # only for grids that declare them: the summaries of the others stay as they were
    if ceilings:
        extra["ceilings"] = ceilings
        # a ceiling per reaction: each policy's failures classed as avoidable or not (grids with one ceiling: absent)
        extra["avoidable_failures"] = avoidable_failures(cfg, pooled)
    if cfg.reaction_comparisons:
        extra["reaction_tests"], families["success_gain_change"] = reaction_tests(cfg, pooled)
    if cfg.disturbance_comparisons:
        extra["disturbance_tests"], sizes = disturbance_tests(cfg, pooled)
        families.update(sizes)
    episodes_from: dict[str, Any] = {}  # a pilot on validation episodes says so; held-out summaries stay as they were
    if cfg.episodes_from != "test":
        part, episode_time = EPISODE_SOURCES[cfg.episodes_from]
        episodes_from["evaluation_episodes"] = {
            "from": cfg.episodes_from,
            "part": part,
            "episode_time": episode_time,
            "description": cfg.episodes_described(),
        }
    summary = {
        "name": cfg.name,
        "config": cfg.source,
        "code_version": code_version(),
        "generated": _now(),
        "splits": list(cfg.splits),
        "seeds": list(cfg.seeds),
        "episodes_per_cell": cfg.episodes,
        "evaluation_seed": cfg.eval_seed,
        **episodes_from,
        "env": dict(cfg.env),
        "complete": not info["missing_cells"],
        "missing_cells": info["missing_cells"],
        "density_bins": edges,
        "policies": policies,
        "ceiling": ceiling,
        "tests": tests,
        **extra,
        "multiple_comparisons": {
            "method": "Holm-Bonferroni within each endpoint",
            "alpha": cfg.alpha,
            "family_sizes": families,
            # the unit of tests with training seeds, where it is not the (seed, episode) pair: absent in older grids
            **({"test_unit": cfg.test_unit} if cfg.test_unit != "pair" else {}),
        },
        "power": cfg.power,
        "wall_time": {
            "cells_s": info["cell_wall_s"],
            "first_start": info["first_start"],
            "last_finish": info["last_finish"],
            "span_s": info["span_s"],
        },
    }
    summary = _clean(summary)
    dest = cfg.out_path()
    where = (
        f"{sources['runs']} cell(s) from run folders, {sources['archive']} cell(s) from the archive "
        f"{archive_path(dest)}"
        + (
            f", {sources['reused']} cell(s) from other grids' results ({', '.join(cfg.reuse)})"
            if sources["reused"]
            else ""
        )
    )
    cells_text = json.dumps(_clean(records), indent=2) + "\n"
    dest.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".summary-", dir=dest))
    try:
        figures = write_plots(summary, staging) if plots else []
        markdown = summary_markdown(summary, cfg, figures)
        old = _load_json(dest / "summary.json")
        unchanged = isinstance(old, dict) and _unchanged(dest, old, summary, cells_text, cfg, figures)
        if unchanged and (stored := stored_as(dest, archive, rows)):
            if stored == "same":
                out(f"{dest}/ is up to date ({where}): no file changed")
            else:
                write_archive(dest, archive, out)
                out(
                    f"{dest}/ is up to date ({where}) but for the archive's layout: wrote {dest / ARCHIVE_DIR}/ "
                    f"({len(archive)} file(s), the same rows); no other file changed"
                )
            return {**summary, **{k: old.get(k) for k in STAMPS}}
        check_replace(cfg, summary, records, sources, force)
        atomic_write_json(staging / "summary.json", summary)
        atomic_write_text(staging / CELLS, cells_text)
        atomic_write_text(staging / "summary.md", markdown)
        write_archive(dest, archive, out)  # the data first: a failure here replaces nothing else
        for name in ["summary.json", CELLS, *(Path(f).name for f in figures), "summary.md"]:
            os.replace(staging / name, dest / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    out(
        f"wrote {dest}/: summary.json, summary.md, cells.json, {ARCHIVE_DIR}/ ({len(archive)} file(s)) and "
        f"{len(figures)} plot(s) ({where})"
    )
    return summary


def _unchanged(
    dest: Path,
    old: dict[str, Any],
    summary: dict[str, Any],
    cells_text: str,
    cfg: AblationConfig,
    figures: list[str],
) -> bool:
    """The files in ``dest`` hold this summary already (stamps aside): same data, same text, every plot there (the
    archive: :func:`agents.ablation.archive.stored_as`)."""
    if _strip(old) != json.loads(json.dumps(_strip(summary))):
        return False
    try:
        same = (dest / CELLS).read_text(encoding="utf-8") == cells_text
        same = same and (dest / "summary.md").read_text(encoding="utf-8") == summary_markdown(
            {**summary, **{k: old.get(k) for k in STAMPS}}, cfg, figures
        )
    except OSError:
        return False
    return same and all((dest / Path(f).name).is_file() for f in figures)
