"""Learning curves: validation success against environment steps, from training run folders.

``python -m agents.curves RUN_DIR [RUN_DIR ...] --out curves.png [--csv curves.csv] [--title TEXT]``
``python -m agents.curves [RUN_DIR ...] --from-csv curves.csv [--predictor ARM] --out curves_ARM.png``

Every run of :mod:`agents.training` validates on the training scenes' validation episodes (``episode_time="val"``;
never the held-out scene) at step 0 (the warm start) and every ``eval.freq_steps`` PPO steps, and writes the
history to ``evaluations.csv`` (step, episodes, success rate and its 95 % Wilson interval, collision and timeout
rates, mean return). :func:`read_curve` reads one run's history with its arm, split and seed (from
``config.yaml``); :func:`plot_curves` draws one line per run (colour by forecast arm, the Wilson band shaded),
one panel per split; :func:`curves_csv` writes every run's points in one table, and :func:`read_curves_csv` reads
such a table back, so the curves of runs whose folders are gone (a grid's run folders are not kept; its
``curves.csv`` is committed) are drawn again, and merged with new runs (a run folder given again replaces its rows).
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import yaml

from crowdnav_mesrnn.utils import atomic_write, atomic_write_text

#: Columns of :func:`curves_csv`.
CURVE_COLUMNS: Final[tuple[str, ...]] = (
    "run", "label", "predictor", "split", "seed", "step", "episodes", "success_rate", "success_lo", "success_hi",
    "collision_rate", "timeout_rate", "mean_return",
)  # fmt: skip
#: Line colours per forecast arm (others cycle through matplotlib's defaults).
ARM_COLOURS: Final[dict[str, str]] = {"none": "#7f7f7f", "cv": "#1f77b4", "mesrnn": "#d62728", "oracle": "#2ca02c"}


@dataclass(frozen=True)
class Curve:
    """One run's validation history.

    Attributes:
        run: the run folder.
        label: what the plot calls it (default: ``<predictor> s<seed>``, plus the folder name when two runs of the
            same arm and seed are drawn together).
        predictor, split, seed: from the run's ``config.yaml``.
        points: one dict per validation, in step order (the columns of ``evaluations.csv``, numbers parsed; a
            history written before the interval columns existed gets them from ``episodes``).
    """

    run: Path
    label: str
    predictor: str
    split: str
    seed: int
    points: list[dict[str, float]]


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def read_curve(run_dir: str | Path, label: str | None = None, episodes: int | None = None) -> Curve:
    """The validation history of a run folder (``evaluations.csv`` and ``config.yaml``).

    Args:
        run_dir: a folder of :mod:`agents.training`.
        label: its name in plots (default: ``<predictor> s<seed>``).
        episodes: validation episodes per point, for histories without an ``episodes`` column (default: the
            config's ``eval.episodes``).

    Raises:
        FileNotFoundError: the folder has no ``evaluations.csv`` (validation off, or not started).
    """
    from agents.stats import wilson_interval  # scipy: not with the command line's parser

    run = Path(run_dir)
    path = run / "evaluations.csv"
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: the run has not validated yet (or eval.episodes is 0)")
    settings: dict[str, Any] = {}
    config = run / "config.yaml"
    if config.is_file():
        doc = yaml.safe_load(config.read_text()) or {}
        settings = doc.get("crowdnav_mesrnn") or {}
    run_info = settings.get("run") or {}
    default_n = episodes if episodes is not None else int((settings.get("eval") or {}).get("episodes") or 0)
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    points = []
    for row in rows:
        point = {k: _number(v) for k, v in row.items() if k != "new_best" and v not in (None, "")}
        n = int(point.get("episodes", default_n))
        if "success_lo" not in point and n > 0:
            lo, hi = wilson_interval(round(point["success_rate"] * n), n)
            point.update(episodes=n, success_lo=lo, success_hi=hi)
        points.append(point)
    points.sort(key=lambda p: p["step"])
    predictor = str(run_info.get("predictor", "?"))
    seed = int(run_info.get("seed", 0))
    return Curve(run, label or f"{predictor} s{seed}", predictor, str(run_info.get("split", "?")), seed, points)


def read_curves_csv(path: str | Path) -> list[Curve]:
    """The curves of a table written by :func:`curves_csv`: one per ``run`` and ``label`` (one run drawn twice under
    two labels is two curves), in the order the table first names them; points in step order.

    Raises:
        ValueError: a missing column, or a row whose number is not finite or whose seed is not an integer (naming the
            file, the line and the column), or a curve whose rows disagree on its predictor, split or seed.
    """
    path = Path(path)
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in CURVE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: not a curves table (python -m agents.curves --csv): missing column(s) {missing}")
        curves: dict[tuple[str, str], tuple[tuple[str, str, int], list[dict[str, float]]]] = {}
        for line, row in enumerate(reader, start=2):
            where = f"{path}, line {line}"
            try:
                seed = int(row["seed"])
            except (TypeError, ValueError):
                raise ValueError(f"{where}: column 'seed' is {row['seed']!r}, not an integer") from None
            point: dict[str, float] = {}
            for col in CURVE_COLUMNS[5:]:
                text = row[col]
                if text in (None, "") and col not in ("step", "success_rate"):
                    continue  # an optional column a history did not have
                value = _number(text or "")
                if not math.isfinite(value):
                    raise ValueError(f"{where}: column {col!r} is {text!r}, not a finite number")
                point[col] = value
            what = (row["predictor"], row["split"], seed)
            old = curves.setdefault((row["run"], row["label"]), (what, []))
            if old[0] != what:
                raise ValueError(
                    f"{where}: run {row['run']!r} ({row['label']!r}) has predictor, split and seed {what} here, "
                    f"{old[0]} above"
                )
            old[1].append(point)
    return [
        Curve(Path(run), label, predictor, split, seed, sorted(points, key=lambda p: p["step"]))
        for (run, label), ((predictor, split, seed), points) in curves.items()
    ]


def merge_curves(old: Sequence[Curve], new: Sequence[Curve]) -> list[Curve]:
    """``old`` (e.g. read from a table) with ``new`` added; the curves of ``new`` whose run ``old`` has replace all of
    ``old``'s curves of that run, where the first of them was."""
    runs = {str(c.run) for c in new}
    out: list[Curve] = []
    for c in old:
        if str(c.run) not in runs:
            out.append(c)
        elif not any(str(o.run) == str(c.run) for o in out):
            out += [n for n in new if str(n.run) == str(c.run)]
    return out + [n for n in new if not any(str(o.run) == str(n.run) for o in old)]


def curves_csv(curves: Sequence[Curve]) -> str:
    """Every point of every curve as CSV text (columns :data:`CURVE_COLUMNS`)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(CURVE_COLUMNS), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for c in curves:
        for p in c.points:
            writer.writerow({"run": str(c.run), "label": c.label, "predictor": c.predictor, "split": c.split,
                             "seed": c.seed, **p})  # fmt: skip
    return buf.getvalue()


def plot_curves(curves: Sequence[Curve], out: str | Path, title: str | None = None) -> Path:
    """Validation success (with its Wilson band) against PPO environment steps, one panel per split, one line per
    run coloured by arm; written atomically to ``out`` (format from the suffix)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not curves:
        raise ValueError("no runs to plot")
    splits = sorted({c.split for c in curves})
    fig, axes = plt.subplots(1, len(splits), figsize=(5.5 * len(splits), 4.0), squeeze=False, sharey=True)
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    others: dict[str, str] = {}
    styles = ("-", "--", ":", "-.")
    for ax, split in zip(axes[0], splits, strict=True):
        seen: dict[str, int] = {}  # runs of one arm in this panel: the same colour, another line style each
        for c in (c for c in curves if c.split == split):
            colour = ARM_COLOURS.get(c.predictor) or others.setdefault(c.predictor, cycle[len(others) % len(cycle)])
            style = styles[seen.get(c.predictor, 0) % len(styles)]
            seen[c.predictor] = seen.get(c.predictor, 0) + 1
            steps = [p["step"] for p in c.points]
            ax.plot(steps, [p["success_rate"] for p in c.points], style, marker="o", ms=3, color=colour, label=c.label)
            if all("success_lo" in p for p in c.points):
                lo = [p["success_lo"] for p in c.points]
                hi = [p["success_hi"] for p in c.points]
                ax.fill_between(steps, lo, hi, color=colour, alpha=0.12, linewidth=0)
        ax.set_title(f"{split} split: validation on its training scenes")
        ax.set_xlabel("PPO environment steps after the warm start")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("validation success rate (95 % Wilson)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out = Path(out)
    fmt = out.suffix.lstrip(".") or "png"
    atomic_write(out, lambda fh: fig.savefig(fh, format=fmt, dpi=120))
    plt.close(fig)
    return out


def add_curves_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="*", help="run folders of agents.train")
    p.add_argument(
        "--from-csv",
        dest="from_csv",
        action="append",
        default=[],
        metavar="CSV",
        help="also the runs of a table written by --csv (repeatable); a run folder given too replaces its rows",
    )
    p.add_argument("--predictor", default=None, help="draw only the runs of this forecast arm (e.g. mesrnn)")
    p.add_argument("--out", required=True, help="the plot (PNG, SVG or PDF by its suffix)")
    p.add_argument("--csv", default=None, help="also write every point of every run to this CSV")
    p.add_argument("--labels", nargs="+", default=None, help="one label per run (default: '<predictor> s<seed>')")
    p.add_argument("--title", default=None, help="a title over the panels")


def run_from_args(args: argparse.Namespace) -> int:
    if args.labels is not None and len(args.labels) != len(args.runs):
        raise ValueError(f"--labels needs one label per run: {len(args.runs)} runs, {len(args.labels)} labels")
    if not args.runs and not args.from_csv:
        raise ValueError("no runs: name run folders, or a table of them with --from-csv")
    labels = args.labels or [None] * len(args.runs)
    curves: list[Curve] = []
    for table in args.from_csv:
        curves = merge_curves(curves, read_curves_csv(table))
    curves = merge_curves(curves, [read_curve(r, label) for r, label in zip(args.runs, labels, strict=True)])
    if args.predictor is not None:
        curves = [c for c in curves if c.predictor == args.predictor]
        if not curves:
            raise ValueError(f"--predictor {args.predictor!r}: no run of that forecast arm")
    out = plot_curves(curves, args.out, args.title)
    print(f"wrote {out}")
    if args.csv:
        atomic_write_text(Path(args.csv), curves_csv(curves))
        print(f"wrote {args.csv}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from agents.entry import module_main

    return module_main("python -m agents.curves", __doc__, add_curves_arguments, run_from_args, argv)


if __name__ == "__main__":
    sys.exit(main())
