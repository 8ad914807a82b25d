""":func:`summarize`: finished evaluation cells into summary.json, summary.md, cells.json, the episode archive, plots."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from agents.ablation.cells import _now
from agents.ablation.config import AblationConfig
from agents.ablation.episodes import _collect, aggregate, episodes_archive
from agents.ablation.plots import write_plots
from agents.ablation.report import summary_markdown
from agents.ablation.stats import _clean, by_density, density_edges, paired_tests
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text, code_version


def summarize(cfg: AblationConfig, out: Callable[[str], None] = print, plots: bool = True) -> dict[str, Any]:
    """Write ``summary.json``, ``summary.md`` and the plots into ``cfg.out_path()``; returns the summary."""
    pooled, info = _collect(cfg)
    edges = density_edges(cfg, pooled)
    policies: dict[str, Any] = {}
    for policy in cfg.policies:
        arms: dict[str, Any] = {}
        for arm in cfg.arms:
            eps = pooled.get((policy.name, arm.label))
            if eps is None:
                continue
            entry: dict[str, Any] = {
                "predictor": arm.predictor,
                "noisy_oracle_ade_m": arm.noisy_oracle_ade_m,
                "seeds": sorted({s for _, s, _ in eps.keys if s is not None}),
                "splits": sorted({sp for sp, _, _ in eps.keys}),
                **aggregate(eps),
            }
            entry["by_split"] = {
                split: aggregate(eps.subset([k[0] == split for k in eps.keys])) for split in entry["splits"]
            }
            entry["by_density"] = by_density(eps, edges)
            arms[arm.label] = entry
        policies[policy.name] = {
            "kind": policy.kind,
            "timesteps": policy.timesteps,
            "n_envs": policy.n_envs if policy.learned else None,
            "model": policy.model if policy.learned else None,
            "agent_config": policy.config,
            "arms": arms,
        }
    tests, families = paired_tests(cfg, pooled)
    summary = {
        "name": cfg.name,
        "config": cfg.source,
        "code_version": code_version(),
        "generated": _now(),
        "splits": list(cfg.splits),
        "seeds": list(cfg.seeds),
        "episodes_per_cell": cfg.episodes,
        "evaluation_seed": cfg.eval_seed,
        "env": dict(cfg.env),
        "complete": not info["missing_cells"],
        "missing_cells": info["missing_cells"],
        "density_bins": edges,
        "policies": policies,
        "tests": tests,
        "multiple_comparisons": {
            "method": "Holm-Bonferroni within each endpoint",
            "alpha": cfg.alpha,
            "family_sizes": families,
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
    dest.mkdir(parents=True, exist_ok=True)
    atomic_write_json(dest / "summary.json", summary)
    atomic_write_json(dest / "cells.json", _clean(info["cells"]))
    archive = episodes_archive(pooled)
    atomic_write(dest / "episodes.csv.gz", lambda fh: fh.write(archive))
    figures = write_plots(summary, dest) if plots else []
    atomic_write_text(dest / "summary.md", summary_markdown(summary, cfg, figures))
    out(f"wrote {dest}/: summary.json, summary.md, cells.json, episodes.csv.gz and {len(figures)} plot(s)")
    return summary
