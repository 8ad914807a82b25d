"""Paired comparison of evaluations on the same episodes: an evaluation folder against others, or against cells of
an ablation grid's episode archive.

``python -m agents.compare EVAL_DIR [EVAL_DIR ...] [--against EVAL_DIR ...] [--grid results/ablation/planning_aid
--cells ppo/mesrnn/0 planner/mesrnn ...] [--json]``

Every evaluation of :mod:`agents.evaluation` on split ``S`` with episode list ``seed`` replays the same seeded
episodes in the same order, so two evaluations (or an evaluation and a grid cell: ``POLICY/ARM[/TRAINING_SEED]``
of the grid's archive, split and list from the evaluation's ``summary.json``) pair episode by episode
on the episodes both hold. Each comparison prints both success rates with 95 % Wilson intervals, the difference
and the exact McNemar test (:func:`agents.stats.mcnemar_exact`). Pilots and single training seeds: the test is
conditional on the trained policies; the seed-level question needs several seeds.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from agents.stats import mcnemar_exact, wilson_interval


def evaluation_successes(folder: str | Path) -> tuple[dict[int, bool], dict[str, Any]]:
    """``({episode index: success}, summary)`` of an evaluation folder (``episodes.csv`` and ``summary.json``)."""
    folder = Path(folder)
    for name in ("episodes.csv", "summary.json"):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{folder / name} does not exist: not an evaluation folder (agents.evaluate --out)")
    with open(folder / "episodes.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    summary = json.loads((folder / "summary.json").read_text())
    return {int(r["episode"]): r["outcome"] == "success" for r in rows}, summary


def grid_rows(path: str | Path) -> list[dict[str, str]]:
    """The episodes of an ablation grid's archive: a results folder (``results/ablation/<name>``, either layout of
    :mod:`agents.ablation.archive`), its ``episodes/`` folder, or one CSV file (``.csv`` or ``.csv.gz``: the older
    single ``episodes.csv.gz``, or one policy's file)."""
    from agents.ablation.archive import ARCHIVE_DIR, has_archive, read_file, read_rows

    path = Path(path)
    if path.is_dir():
        folder = path.parent if path.name == ARCHIVE_DIR and not has_archive(path) else path
        if not has_archive(folder):
            raise FileNotFoundError(f"{path} holds no episode archive ({ARCHIVE_DIR}/ or episodes.csv.gz)")
        return read_rows(folder)
    if path.name.endswith(".gz"):
        return read_file(path)  # a damaged file: an error naming it
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def grid_successes(path: str | Path, cell: str, split: str) -> dict[int, bool]:
    """``{episode index: success}`` of a grid cell ``POLICY/ARM[/TRAINING_SEED]`` on ``split`` in an ablation grid's
    archive (:func:`grid_rows`)."""
    parts = cell.split("/")
    if len(parts) not in (2, 3):
        raise ValueError(f"a grid cell is POLICY/ARM or POLICY/ARM/TRAINING_SEED, got {cell!r}")
    out = {
        int(r["episode"]): r["outcome"] == "success"
        for r in grid_rows(path)
        if r["split"] == split and r["policy"] == parts[0] and r["arm"] == parts[1]
        and (len(parts) == 2 or r["seed"] == parts[2])
    }  # fmt: skip
    if not out:
        raise ValueError(f"{path} holds no episodes of cell {cell!r} on split {split!r}")
    return out


def _rate(successes: Sequence[bool]) -> dict[str, Any]:
    k, n = int(sum(successes)), len(successes)
    return {"successes": k, "episodes": n, "rate": k / n, "ci": list(wilson_interval(k, n))}


def paired(a: Mapping[int, bool], b: Mapping[int, bool]) -> dict[str, Any]:
    """Both rates on the episodes both hold, the difference ``a - b`` and the exact McNemar test."""
    common = sorted(set(a) & set(b))
    if not common:
        raise ValueError("the two sets of episodes have none in common")
    xa, xb = [a[e] for e in common], [b[e] for e in common]
    test = mcnemar_exact(xa, xb)
    return {"a": _rate(xa), "b": _rate(xb), "difference": test["difference"], "p_value": test["p_value"]}


def _fmt(r: Mapping[str, Any]) -> str:
    return (
        f"{100 * r['rate']:5.1f} % [{100 * r['ci'][0]:.1f}, {100 * r['ci'][1]:.1f}] ({r['successes']}/{r['episodes']})"
    )


def add_compare_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("evaluations", nargs="+", help="evaluation folders (agents.evaluate --out)")
    p.add_argument("--against", nargs="*", default=[], help="other evaluation folders to pair with")
    p.add_argument(
        "--grid",
        default=None,
        help="an ablation grid's results folder (e.g. results/ablation/planners) or archive file holding the cells of "
        "--cells",
    )
    p.add_argument("--cells", nargs="*", default=[], help="grid cells POLICY/ARM[/TRAINING_SEED], e.g. ppo/mesrnn/0")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run_from_args(args: argparse.Namespace) -> int:
    if args.cells and not args.grid:
        raise ValueError("--cells needs --grid (an ablation grid's results folder)")
    results: dict[str, Any] = {}
    for folder in args.evaluations:
        mine, summary = evaluation_successes(folder)
        split = str(summary["split"])
        refs: list[tuple[str, Mapping[int, bool]]] = [(str(f), evaluation_successes(f)[0]) for f in args.against]
        refs += [(f"grid {c}", grid_successes(args.grid, c, split)) for c in args.cells]
        entry = {"split": split, "predictor": summary.get("predictor"), "alone": _rate(list(mine.values()))}
        entry["against"] = {name: paired(mine, ref) for name, ref in refs}
        results[str(folder)] = entry
        if not args.json:
            print(f"{folder} ({entry['predictor']} forecasts, {split}): {_fmt(entry['alone'])}")
            for name, r in entry["against"].items():
                print(f"   vs {name:<40} {_fmt(r['b'])}   difference {100 * r['difference']:+5.1f} points, "
                      f"McNemar p = {r['p_value']:.3g} on {r['a']['episodes']} paired episodes")  # fmt: skip
    if args.json:
        print(json.dumps(results))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from agents.entry import module_main

    return module_main("python -m agents.compare", __doc__, add_compare_arguments, run_from_args, argv)


if __name__ == "__main__":
    sys.exit(main())
