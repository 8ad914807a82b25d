"""The policy bench's one page: ``report.md``, ``report.json`` and ``success_by_scene.png``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from agents.ablation.report import _mean as mean_with_interval
from agents.policy_bench.references import REFERENCE_LABELS
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text

#: Where a reference's episodes came from, as the page says it.
SOURCES: dict[str, str] = {
    "committed": "the committed planner grid (results/ablation/planners/), the same episodes",
    "cached": "an earlier bench in this folder",
    "run": "run by this bench",
}


def _pct(cell: Mapping[str, Any], outcome: str = "success") -> str:
    rate, ci = cell.get(f"{outcome}_rate"), cell.get(f"{outcome}_ci")
    if rate is None:
        return "—"
    return f"{100 * rate:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def _mean(cell: Mapping[str, Any], key: str, digits: int = 2) -> str:
    return mean_with_interval(cell, key, digits, missing="—")


def _signed(x: float) -> str:
    return f"{x:+.1f}".replace("-", "−")


def _rows(report: Mapping[str, Any]) -> list[tuple[str, str, str, Mapping[str, Any]]]:
    """``(scene, who, arm, cell)`` in page order: per scene and arm the policy, then the references."""
    out = []
    for split, scene in report["scenes"].items():
        for arm, cell in scene["policy"].items():
            out.append((split, "policy", arm, cell))
            for name, cells in scene["references"].items():
                for ref_arm, ref in cells.items():
                    if ref_arm == arm:
                        out.append((split, name, arm, ref))
        for name, cells in scene["references"].items():  # the ceiling's one arm, once per scene
            for ref_arm, ref in cells.items():
                if ref_arm not in scene["policy"]:
                    out.append((split, name, ref_arm, ref))
    return out


def render_markdown(report: Mapping[str, Any]) -> str:
    """The page: what ran, success and metrics per scene and arm beside the references, the paired tests."""
    cfg = report["config"]
    name = report["policy"]
    lines = [
        f"# Policy bench: `{name}`",
        "",
        f"Written by `{report['command']}` (code {report['code_version']}, environment revision "
        f"{report['env_revision']}) in {report['seconds']:.0f} s. The policy (`{report['policy_kind']}`) crossed the "
        f"held-out scenes {', '.join(report['scenes'])} with forecast arms {', '.join(cfg['arms'])}: the first "
        f"{cfg['episodes']} episodes of each scene's fixed list (list {cfg['seed']}, the planner grids' lists), the "
        "same episodes as every reference below." + (f" Environment overrides: `{cfg['env']}`." if cfg["env"] else ""),
        "",
        "References: the sampling planner, the search planner (no `none` arm: there it extrapolates observed "
        "velocities, i.e. its `cv` arm) and the privileged ceiling, which reads the replay's true future of every "
        "pedestrian (PRIVILEGED: a measuring stick, not a competitor; one arm, its forecast input unused). Where "
        "their episodes came from is in the last column.",
        "",
        "## Success and the metrics reviewers ask for",
        "",
        "Rates in % with 95 % Wilson intervals; means with 95 % bootstrap intervals. SPL: success weighted by path "
        "length to the required distance (straight line minus goal tolerance); path ratio: path length / required "
        "distance (successes); min clearance: closest surface distance to a pedestrian; min TTC: smallest "
        "constant-velocity time to collision (episodes that had one). Definitions: docs/env.md. '—': not recorded "
        "(references from the committed grid predate these metrics; `--rerun-references` runs them here).",
        "",
        "| scene | arm | who | success % | collision % | timeout % | SPL | path ratio | min clearance m | "
        "min TTC s | episodes from |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for split, who, arm, cell in _rows(report):
        label = f"**{name}**" if who == "policy" else REFERENCE_LABELS[who].split(" (")[0]
        source = "this bench" if who == "policy" else SOURCES.get(cell.get("source", ""), "—")
        lines.append(
            f"| {split} | {arm} | {label} | {_pct(cell)} | {_pct(cell, 'collision')} | {_pct(cell, 'timeout')} | "
            f"{_mean(cell, 'spl')} | {_mean(cell, 'path_ratio_required')} | {_mean(cell, 'min_clearance_m')} | "
            f"{_mean(cell, 'min_ttc_s')} | {source} |"
        )
    tests = report["tests"]
    lines += [
        "",
        "## Paired tests",
        "",
        f"Success of the policy against each reference on the same episodes: exact McNemar test, Holm-corrected "
        f"over the {len(tests)} tests. The interval is the exact conditional one that matches the test (excludes 0 "
        f"exactly when p < 0.05); the verdict reads the Holm-adjusted p at alpha = {report['alpha']}, so an interval "
        "can exclude 0 and the verdict still be 'no difference shown' once the number of tests is counted; 'no "
        "difference shown' is not a finding of equality.",
        "",
        "| scene | arm | policy − reference | difference, points [95 %] | b10 / b01 | p | Holm p | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for t in tests:
        lo, hi = t["difference_exact_ci"]
        ref = REFERENCE_LABELS[t["reference"]].split(" (")[0] + (
            f" ({t['reference_arm']})" if t["reference_arm"] != t["arm"] else ""
        )
        verdict = t["verdict"]
        if verdict in ("better", "worse"):
            verdict = f"{verdict} than the {ref}"
        lines.append(
            f"| {t['scene']} | {t['arm']} | {name} − {ref} | {_signed(100 * t['difference'])} "
            f"[{_signed(100 * lo)}, {_signed(100 * hi)}] | {t['b10']} / {t['b01']} | {t['p_value']:.3g} | "
            f"{t['p_holm']:.3g} | {verdict} |"
        )
    lines += ["", "![success per scene and arm](success_by_scene.png)", ""]
    return "\n".join(lines)


#: Marker, colour and offset of each side in the plot.
_STYLE: dict[str, tuple[str, str, float]] = {
    "policy": ("s", "C3", -0.24),
    "sampling": ("o", "C0", -0.08),
    "search": ("^", "C1", 0.08),
    "privileged": ("D", "C2", 0.24),
}


def plot_success(report: Mapping[str, Any], path: Path) -> Path:
    """One panel per arm: success % per scene with Wilson intervals for the policy and the references."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = list(report["config"]["arms"])
    scenes = list(report["scenes"])
    fig, axes = plt.subplots(1, len(arms), figsize=(3.2 + 2.6 * len(arms), 3.8), squeeze=False, sharey=True)
    for ax, arm in zip(axes[0], arms, strict=True):
        for who, (marker, colour, dx) in _STYLE.items():
            xs, ys, err = [], [], [[], []]
            for i, split in enumerate(scenes):
                scene = report["scenes"][split]
                if who == "policy":
                    cell = scene["policy"].get(arm)
                else:
                    cells = scene["references"].get(who, {})
                    cell = cells.get(arm) or (next(iter(cells.values())) if who == "privileged" and cells else None)
                if not cell or cell.get("success_rate") is None:
                    continue
                y = 100 * cell["success_rate"]
                lo, hi = (100 * v for v in cell["success_ci"])
                xs.append(i + dx)
                ys.append(y)
                err[0].append(y - lo)
                err[1].append(hi - y)
            if xs:
                label = report["policy"] if who == "policy" else REFERENCE_LABELS[who].split(" (")[0]
                ax.errorbar(xs, ys, yerr=err, fmt=marker, color=colour, ms=6, capsize=3, label=label)
        ax.set_xticks(range(len(scenes)), scenes)
        ax.set_xlim(-0.6, len(scenes) - 0.4)
        ax.set_title(f"forecast arm: {arm}")
        ax.set_ylim(-2, 102)
        ax.grid(alpha=0.3, axis="y")
    axes[0][0].set_ylabel("success (%), 95 % Wilson interval")
    legend: dict[str, Any] = {}
    for ax in axes[0]:  # every side once, whichever panel has it (the search planner has no none arm)
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(label, handle)
    fig.legend(list(legend.values()), list(legend), loc="lower center", ncol=len(legend), fontsize=8, frameon=False)
    fig.suptitle(f"Policy bench: {report['policy']} ({report['config']['episodes']} episodes per scene and arm)")
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)
    return path


def write_report(report: Mapping[str, Any], out_dir: Path) -> dict[str, Path]:
    """Write ``report.json``, ``success_by_scene.png`` and ``report.md``, each atomically."""
    return {
        "json": atomic_write_json(out_dir / "report.json", report),
        "png": plot_success(report, out_dir / "success_by_scene.png"),
        "md": atomic_write_text(out_dir / "report.md", render_markdown(report)),
    }
