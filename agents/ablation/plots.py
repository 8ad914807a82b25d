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

#: Arms drawn in the density plot, each in its own fixed colour (the sweep and the other predictors are in
#: ``rates_vs_ade.png``; ten lines in one panel cannot be told apart).
DENSITY_ARMS: dict[str, str] = {
    "none": "tab:grey",
    "cv": "tab:blue",
    "mesrnn": "tab:orange",
    "oracle": "tab:green",
    "cv_unc": "tab:cyan",
    "mesrnn_unc": "tab:brown",
}


def _edge(value: float) -> str:
    """A density bin edge: whole pedestrians as integers, others to one decimal."""
    return f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"


def _err(entry: Mapping[str, Any], key: str) -> tuple[float, float, float]:
    rate = entry.get(f"{key}_rate")
    lo, hi = entry.get(f"{key}_ci") or (None, None)
    if rate is None or lo is None or hi is None:
        return (math.nan, 0.0, 0.0)
    return (rate, max(rate - lo, 0.0), max(hi - rate, 0.0))


def write_plots(summary: Mapping[str, Any], dest: Path) -> list[str]:
    """Rates per arm; success/collision against closed-loop forecast ADE; success by crowd density; and, for a grid
    with reacting pedestrians, each declared gain on the replay and under each reaction."""
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
                if ade is None:  # the none arm: a horizontal reference, labelled at the right edge
                    ax.axhline(r, color=colours[o], ls=":", lw=1)
                    ax.annotate(
                        f"{arm} ({o})",
                        (1.0, r),
                        xycoords=("axes fraction", "data"),
                        fontsize=7,
                        color=colours[o],
                        ha="right",
                        va="bottom",
                    )
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
            if o == "success":  # arm names once per arm (collision points share the x of their success point)
                _label_points(ax, [(p[0], p[1], p[4]) for p in pts])
        ax.set_title(name)
        ax.set_xlabel("closed-loop forecast ADE (m)")
        ax.set_ylim(0, 1)
    written.append(_finish(fig, axes, dest / "rates_vs_ade.png"))

    edges = summary.get("density_bins") or []
    if len(edges) >= 2:
        fig, axes = plt.subplots(2, len(policies), figsize=(5 * len(policies), 6), squeeze=False, sharey=True)
        labels = [f"{_edge(lo)}-{_edge(hi)}" for lo, hi in itertools.pairwise(edges)]
        for col, (name, pol) in enumerate(policies.items()):
            shown = {a: e for a, e in pol["arms"].items() if a in DENSITY_ARMS} or pol["arms"]
            for row, o in enumerate(("success", "collision")):
                ax = axes[row][col]
                n_arms = max(len(shown), 1)
                for k, (arm, e) in enumerate(shown.items()):
                    vals = np.asarray([_err(b, o) for b in e["by_density"]])
                    if vals.size == 0:
                        continue
                    x = np.arange(len(vals)) + (k - (n_arms - 1) / 2) * 0.8 / n_arms
                    colour = DENSITY_ARMS.get(arm)
                    ax.errorbar(x, vals[:, 0], yerr=vals[:, 1:].T, fmt="o-", capsize=2, label=arm, ms=3, color=colour)
                ax.set_xticks(np.arange(len(labels)), labels)
                ax.set_ylim(0, 1)
                ax.set_title(f"{name}: {o}")
                if row == 1:
                    ax.set_xlabel("crowd density: mean pedestrians near the path")
        axes[0][0].set_ylabel("success rate")
        axes[1][0].set_ylabel("collision rate")
        fig.tight_layout(rect=(0.0, 0.0, 1.0, _figure_legend(fig, axes)))
        written.append(str(_save(fig, dest / "rates_by_density.png")))
        plt.close(fig)
    tests = [t for t in summary.get("reaction_tests") or [] if not t.get("missing")]
    if tests:
        written.append(_gains_by_reaction(tests, dest / "gains_by_reaction.png"))
    return written


#: Colours of the reactions in ``gains_by_reaction.png`` (the replay grey).
REACTION_COLOURS: dict[str, str] = {
    "none": "tab:grey",
    "orca": "tab:blue",
    "pause": "tab:orange",
    "social_force": "tab:purple",
}


def _gains_by_reaction(tests: list[Mapping[str, Any]], path: Path) -> str:
    """Each declared gain (``a - b`` in success, points, with its bootstrap interval) on the replay and under each
    reaction, one panel per planner: does a forecast's gain survive when people react?"""
    import matplotlib.pyplot as plt

    planners = list(dict.fromkeys(t["planner"] for t in tests))
    fig, axes = plt.subplots(1, len(planners), figsize=(5.5 * len(planners), 3.8), squeeze=False, sharey=True)
    for ax, planner in zip(axes[0], planners, strict=True):
        mine = [t for t in tests if t["planner"] == planner]
        gains = list(dict.fromkeys(f"{t['gain']['a']} - {t['gain']['b']}" for t in mine))
        reactions = [mine[0]["baseline"], *dict.fromkeys(t["reaction"] for t in mine)]
        width = 0.8 / len(reactions)
        for k, reaction in enumerate(reactions):
            xs, ys, errs = [], [], []
            for g, gain in enumerate(gains):
                t = next((t for t in mine if f"{t['gain']['a']} - {t['gain']['b']}" == gain
                          and reaction in (t["reaction"], t["baseline"])), None)  # fmt: skip
                if t is None:
                    continue
                key = "gain_baseline" if reaction == t["baseline"] else "gain_reaction"
                value, (lo, hi) = 100 * t[key], t[f"{key}_ci"]
                xs.append(g + (k - (len(reactions) - 1) / 2) * width)
                ys.append(value)
                errs.append((max(value - 100 * lo, 0.0), max(100 * hi - value, 0.0)))
            label = f"{reaction} (replay)" if k == 0 else reaction
            colour = REACTION_COLOURS.get(reaction)
            ax.bar(xs, ys, width, yerr=np.asarray(errs).reshape(-1, 2).T, capsize=2, color=colour, label=label)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xticks(np.arange(len(gains)), gains)
        name = {"planner": "sampling planner", "search": "search planner"}.get(planner, planner)
        ax.set_title(f"{name}: gain in success, pooled over splits")
    axes[0][0].set_ylabel("points (95 % bootstrap CI)")
    fig.tight_layout(rect=(0.0, 0.0, 1.0, _figure_legend(fig, axes)))
    saved = _save(fig, path)
    plt.close(fig)
    return str(saved)


def _label_points(ax: Any, points: list[tuple[float, float, str]]) -> None:
    """Name each point without labels overlapping: labels of points closer than a tenth of the x range are stacked
    at least 4 % of the y range apart, and joined to their point by a thin line when moved."""
    if not points:
        return
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    near, gap = 0.1 * (x1 - x0), 0.065 * (y1 - y0)
    placed: list[tuple[float, float]] = []
    for x, y, name in sorted(points, key=lambda p: (-p[1], p[0])):
        ly = y + 0.02 * (y1 - y0)
        while any(abs(x - px) < near and abs(ly - py) < gap for px, py in placed):
            ly -= gap
        placed.append((x, ly))
        moved = abs(ly - y) > 0.04 * (y1 - y0)
        ax.annotate(
            name,
            (x, y),
            xytext=(x + 0.03 * (x1 - x0), ly),
            fontsize=7,
            va="center",
            arrowprops={"arrowstyle": "-", "lw": 0.6, "color": "0.4", "shrinkA": 0, "shrinkB": 3} if moved else None,
        )


def _figure_legend(fig: Any, axes: Any) -> float:
    """One legend for the whole figure, above the panels (never over a bar or a point); returns the top of the
    panels' area (a figure fraction) to leave it room."""
    for ax in np.ravel(axes):
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 6), fontsize=8, frameon=False)
            rows = math.ceil(len(labels) / 6)
            return 1.0 - (0.1 + 0.25 * rows) / fig.get_figheight()
    return 1.0


def _finish(fig: Any, axes: Any, path: Path) -> str:
    """Label and save a figure of rates (one legend above the panels), then close it."""
    import matplotlib.pyplot as plt

    for row in axes:
        row[0].set_ylabel("rate (95 % Wilson CI)")
    fig.tight_layout(rect=(0.0, 0.0, 1.0, _figure_legend(fig, axes)))
    saved = _save(fig, path)
    plt.close(fig)
    return str(saved)


def _save(fig: Any, path: Path) -> Path:
    return atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
