"""The ablation's plots."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from agents.ablation.config import OUTCOMES
from crowdnav_mesrnn.utils import atomic_write


def _err(entry: Mapping[str, Any], key: str) -> tuple[float, float, float]:
    rate = entry.get(f"{key}_rate")
    lo, hi = entry.get(f"{key}_ci") or (None, None)
    if rate is None or lo is None or hi is None:
        return (math.nan, 0.0, 0.0)
    return (rate, max(rate - lo, 0.0), max(hi - rate, 0.0))


def write_plots(summary: Mapping[str, Any], dest: Path) -> list[str]:
    """Rates per arm; success/collision against closed-loop forecast ADE; success by crowd density."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    policies = {k: v for k, v in summary["policies"].items() if v["arms"]}
    if not policies:
        return []
    written: list[str] = []
    colours = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:grey"}

    # one row pooled over splits, then one row per split (splits differ in difficulty, so pooling alone hides them)
    views: list[str | None] = [None, *summary["splits"]] if len(summary["splits"]) > 1 else [None]
    fig, axes = plt.subplots(
        len(views), len(policies), figsize=(5 * len(policies), 3.6 * len(views)), squeeze=False, sharey=True
    )
    for row, view in enumerate(views):
        for ax, (name, pol) in zip(axes[row], policies.items(), strict=True):
            entries = {a: (e if view is None else e.get("by_split", {}).get(view)) for a, e in pol["arms"].items()}
            arms = [a for a, e in entries.items() if e]
            x = np.arange(len(arms))
            for j, o in enumerate(OUTCOMES):
                vals = np.asarray([_err(entries[a], o) for a in arms]).reshape(-1, 3)
                ax.bar(x + (j - 1) * 0.27, vals[:, 0], 0.27, yerr=vals[:, 1:].T, color=colours[o], label=o, capsize=2)
            ax.set_xticks(x, arms, rotation=30, ha="right")
            ax.set_title(f"{name}, {'pooled over splits' if view is None else view}")
            ax.set_ylim(0, 1)
    written.append(_finish(fig, axes, dest / "rates_by_arm.png"))

    fig, axes = plt.subplots(1, len(policies), figsize=(5 * len(policies), 3.6), squeeze=False, sharey=True)
    for ax, (name, pol) in zip(axes[0], policies.items(), strict=True):
        for o in ("success", "collision"):
            pts = []
            for arm, e in pol["arms"].items():
                ade = e.get("forecast_ade_m_mean")
                if e["predictor"] == "oracle" and ade is None:
                    ade = 0.0
                r, lo, hi = _err(e, o)
                if ade is None:  # the none arm: a horizontal reference
                    ax.axhline(r, color=colours[o], ls=":", lw=1)
                    ax.annotate(f"{arm} ({o})", (0.0, r), fontsize=7, color=colours[o], va="bottom")
                    continue
                pts.append((ade, r, lo, hi, arm, e["predictor"]))
            pts.sort()
            if not pts:
                continue
            arr = np.asarray([p[:4] for p in pts], dtype=float)
            ax.errorbar(arr[:, 0], arr[:, 1], yerr=arr[:, 2:].T, fmt="o", color=colours[o], capsize=2, label=o)
            sweep = np.asarray([p[:2] for p in pts if p[5] in ("noisy_oracle", "oracle")], dtype=float)
            if len(sweep) > 1:
                ax.plot(sweep[:, 0], sweep[:, 1], "--", color=colours[o], lw=1)
            for ade, r, _, _, arm, _ in pts:
                ax.annotate(arm, (ade, r), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(name)
        ax.set_xlabel("closed-loop forecast ADE (m)")
        ax.set_ylim(0, 1)
    written.append(_finish(fig, axes, dest / "rates_vs_ade.png"))

    edges = summary.get("density_bins") or []
    if len(edges) >= 2:
        fig, axes = plt.subplots(2, len(policies), figsize=(5 * len(policies), 6), squeeze=False, sharey=True)
        labels = [f"{lo:.1f}-{hi:.1f}" for lo, hi in itertools.pairwise(edges)]
        for col, (name, pol) in enumerate(policies.items()):
            for row, o in enumerate(("success", "collision")):
                ax = axes[row][col]
                n_arms = max(len(pol["arms"]), 1)
                for k, (arm, e) in enumerate(pol["arms"].items()):
                    vals = np.asarray([_err(b, o) for b in e["by_density"]])
                    if vals.size == 0:
                        continue
                    x = np.arange(len(vals)) + (k - (n_arms - 1) / 2) * 0.8 / n_arms
                    ax.errorbar(x, vals[:, 0], yerr=vals[:, 1:].T, fmt="o-", capsize=2, label=arm, ms=3)
                ax.set_xticks(np.arange(len(labels)), labels)
                ax.set_ylim(0, 1)
                ax.set_title(f"{name}: {o}")
                if row == 1:
                    ax.set_xlabel("crowd density (pedestrians near the path)")
            if axes[0][col].get_legend_handles_labels()[0]:
                axes[0][col].legend(fontsize=7)
        axes[0][0].set_ylabel("success rate")
        axes[1][0].set_ylabel("collision rate")
        fig.tight_layout()
        written.append(str(_save(fig, dest / "rates_by_density.png")))
        plt.close(fig)
    return written


def _finish(fig: Any, axes: Any, path: Path) -> str:
    """Label and save a figure of rates (legends in the first row), then close it."""
    import matplotlib.pyplot as plt

    for row in axes:
        row[0].set_ylabel("rate (95 % Wilson CI)")
    for ax in axes[0]:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    saved = _save(fig, path)
    plt.close(fig)
    return str(saved)


def _save(fig: Any, path: Path) -> Path:
    return atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
