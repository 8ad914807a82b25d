"""The bench's one-page report: ``report.md``, ``report.json`` and ``success_vs_ade.png``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text


def _m(x: float | None, digits: int = 3) -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _signed(x: float, digits: int = 3) -> str:
    return f"{x:+.{digits}f}".replace("-", "−")


def _ci(ci: list[float], digits: int = 3) -> str:
    return f"[{_signed(ci[0], digits)}, {_signed(ci[1], digits)}]"


def _plain(verdict: str, reference: str) -> str:
    """A planner cell's verdict as a phrase: ``better than cv``, ``worse than cv``, ``no difference shown``."""
    return f"{verdict} than {reference}" if verdict in ("better", "worse") else verdict


def _verdict(ci: list[float]) -> str:
    if ci[1] < 0:
        return "better than CV"
    if ci[0] > 0:
        return "worse than CV"
    return "not detectably different from CV"


def render_markdown(report: Mapping[str, Any]) -> str:
    """The page: the predictor's identity, ADE/FDE against CV, the planner cells and the paired tests."""
    name = report["predictor"]
    lines = [f"# Bench: `{name}`", ""]
    spec = report.get("spec") or {}
    lines += [
        f"Predictor `{name}` (factory `{spec.get('target')}`, distribution {spec.get('distribution') or '—'} "
        f"{spec.get('version') or ''}). Written by `{report['command']}` (code {report['code_version']}).",
        "",
    ]
    metrics = report.get("predictor_metrics")
    if metrics:
        lines += [
            "## Forecast accuracy on the test windows",
            "",
            f"ETH/UCY leave-one-out test parts, windows with at least two scored pedestrians, ADE/FDE in metres over "
            f"12 steps. Differences are {name} − constant velocity on the same windows (negative: better), with 95 % "
            f"moving-block bootstrap intervals (blocks of {metrics['block_len']} windows, {metrics['resamples']:,} "
            "resamples); the average is the unweighted mean of the splits.",
            "",
            f"| split | windows | ADE {name} | ADE CV | ADE diff [95 %] | FDE {name} | FDE CV | FDE diff [95 %] |",
            "|---|---|---|---|---|---|---|---|",
        ]
        rows = dict(metrics["splits"])
        if "average" in metrics:
            rows["average"] = metrics["average"]
        for split, r in rows.items():
            lines.append(
                f"| {split} | {r.get('windows', '')} | {_m(r['ade_m'])} | {_m(r['cv_ade_m'])} | "
                f"{_signed(r['ade_m_diff'])} {_ci(r['ade_m_diff_ci'])} | {_m(r['fde_m'])} | {_m(r['cv_fde_m'])} | "
                f"{_signed(r['fde_m_diff'])} {_ci(r['fde_m_diff_ci'])} |"
            )
        if "average" in metrics:
            lines += ["", f"On the average, {name}'s ADE is {_verdict(metrics['average']['ade_m_diff_ci'])}."]
        lines.append("")
    planner = report.get("planner")
    if planner:
        lines += [
            "## The sampling planner with these forecasts",
            "",
            f"The planner cells of the planning-aid ablation on the held-out scenes, {report['episodes']} seeded "
            "episodes per cell (the same list in every arm of a scene), success % with 95 % Wilson intervals; "
            "forecast ADE is closed-loop (forecasts made during the episodes, scored against the replay).",
            "",
            "| scene | arm | success % [95 %] | forecast ADE m |",
            "|---|---|---|---|",
        ]
        for scene, arms in planner["arms"].items():
            for arm, a in arms.items():
                lo, hi = a["success_ci"]
                lines.append(
                    f"| {scene} | {arm} | {100 * a['success_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}] | "
                    f"{_m(a['forecast_ade_m'])} |"
                )
        lines += [
            "",
            f"Paired tests on the same episodes (exact McNemar on success), Holm-corrected over the "
            f"{len(planner['tests'])} tests. The interval is the exact conditional one that matches the test (the "
            "Clopper-Pearson interval of how the discordant episodes split, mapped onto the difference): it "
            "excludes 0 exactly when p < 0.05. The verdict reads the Holm-adjusted p at "
            f"alpha = {planner.get('alpha', 0.05)}: an interval can exclude 0 and the verdict still be 'no "
            "difference shown' once the number of tests is counted; 'no difference shown' is not a finding of "
            "equality.",
            "",
            "| scene | comparison | difference, points [95 %] | p | Holm p | verdict |",
            "|---|---|---|---|---|---|",
        ]
        for t in planner["tests"]:
            lo, hi = t["difference_exact_ci"]
            lines.append(
                f"| {t['scene']} | {t['a']} − {t['b']} | {_signed(100 * t['difference'], 1)} "
                f"[{_signed(100 * lo, 1)}, {_signed(100 * hi, 1)}] | {t['p_value']:.3g} | {t['p_holm']:.3g} | "
                f"{_plain(t['verdict'], t['b'])} |"
            )
        lines += [
            "",
            "![success against closed-loop forecast ADE](success_vs_ade.png)",
            "",
            "The noisy-oracle curve (true future plus an error growing over the horizon, at a target ADE) places the "
            "predictor: a point above the curve plans better than its ADE alone suggests.",
            "",
        ]
    else:
        lines += ["The planner cells were not run (`--no-planner`).", ""]
    return "\n".join(lines).rstrip() + "\n"


#: Marker and colour of the reference arms in the plot.
_STYLE = {"cv": ("o", "C0"), "oracle": ("D", "C2")}


def plot_success_vs_ade(report: Mapping[str, Any], path: Path) -> Path:
    """Per scene: success % against closed-loop forecast ADE, the noisy-oracle curve and the labelled arms."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    planner = report["planner"]
    scenes = list(planner["arms"])
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.2), squeeze=False, sharey=True)
    for ax, scene in zip(axes[0], scenes, strict=True):
        arms = planner["arms"][scene]
        noisy = sorted(
            (a["forecast_ade_m"], 100 * a["success_rate"])
            for a in arms.values()
            if a["noisy_oracle_ade_m"] is not None and a["forecast_ade_m"] is not None
        )
        oracle = arms.get("oracle")
        if oracle is not None:
            noisy = [(0.0, 100 * oracle["success_rate"]), *noisy]
        if noisy:
            ax.plot(*zip(*noisy, strict=True), "-o", color="0.6", label="noisy oracle (reference)", zorder=1)
        for arm, a in arms.items():
            if a["noisy_oracle_ade_m"] is not None:
                continue
            x = 0.0 if arm == "oracle" else a["forecast_ade_m"]
            if x is None:
                continue
            y = 100 * a["success_rate"]
            lo, hi = (100 * v for v in a["success_ci"])
            fmt, color = _STYLE.get(arm, ("s", "C3"))  # the benchmarked predictor: red squares
            ax.errorbar(x, y, yerr=[[y - lo], [hi - y]], fmt=fmt, color=color, ms=7, capsize=3, zorder=3, label=arm)
        ax.set_title(f"held-out scene: {scene}")
        ax.set_xlabel("closed-loop forecast ADE (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best", framealpha=0.9)
    axes[0][0].set_ylabel("planner success (%)")
    fig.suptitle(f"Sampling planner success against forecast error: {report['predictor']}")
    fig.tight_layout()
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)
    return path


def write_report(report: Mapping[str, Any], out_dir: Path) -> dict[str, Path]:
    """Write ``report.json``, ``report.md`` and (with planner cells) ``success_vs_ade.png``, each atomically."""
    out = {"json": atomic_write_json(out_dir / "report.json", report)}
    if report.get("planner"):
        out["png"] = plot_success_vs_ade(report, out_dir / "success_vs_ade.png")
    out["md"] = atomic_write_text(out_dir / "report.md", render_markdown(report))
    return out
