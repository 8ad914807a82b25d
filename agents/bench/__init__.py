"""``crowdnav-mesrnn bench PREDICTOR``: the project's navigation answer for any predictor, on one page.

Two halves, each resumable and cached under ``--out``:

1. :mod:`agents.bench.metrics` — ADE/FDE on the ETH/UCY leave-one-out test windows against constant velocity
   (paired, block-bootstrap intervals);
2. :mod:`agents.bench.planner` — the sampling planner on the held-out scenes with the predictor's forecasts,
   against cv, the oracle and the noisy-oracle sweep on the same episodes (exact McNemar, Holm).

:mod:`agents.bench.report` writes ``report.md``, ``report.json`` and ``success_vs_ade.png``. The planner cells run
on the ablation's grid machinery (:mod:`agents.ablation`: a local process pool, or Ray with ``--backend ray``).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from agents.bench.metrics import predictor_metrics
from agents.bench.planner import (
    DEFAULT_SCENES,
    NOISY_ORACLE_ADE_M,
    bench_grid,
    planner_results,
    run_planner_cells,
)
from agents.bench.report import write_report
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP
from crowdnav_mesrnn.evaluation.statistics import DEFAULT_BLOCK_LEN

__all__ = ["BenchConfig", "run_bench"]


@dataclass(frozen=True)
class BenchConfig:
    """What one bench runs."""

    predictor: str
    """Predictor name (shipped, installed plug-in) or import path ``package.module:Factory``."""
    splits: tuple[str, ...] = SPLITS
    """Leave-one-out splits whose test windows are scored (ADE/FDE)."""
    scenes: tuple[str, ...] = DEFAULT_SCENES
    """Held-out scenes (splits) of the planner cells."""
    episodes: int = 500
    """Seeded episodes per planner cell (the ablation uses 500)."""
    seed: int = 0
    """Which seeded list of episodes."""
    noisy_oracle_ade_m: tuple[float, ...] = NOISY_ORACLE_ADE_M
    """Target ADEs of the noisy-oracle reference arms, metres."""
    planner: bool = True
    """Run the planner cells (False: forecast accuracy only)."""
    block_len: int = DEFAULT_BLOCK_LEN
    """Moving-block length of the bootstrap, windows."""
    resamples: int = 10_000
    """Bootstrap resamples."""


def default_out(predictor: str) -> Path:
    """``runs/bench/<predictor>`` (an import path's ``:`` and ``.`` made file-name safe)."""
    return Path("runs") / "bench" / predictor.replace(":", "_").replace("/", "_")


def run_bench(
    cfg: BenchConfig,
    out_dir: str | Path,
    *,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    command: str = "",
    force: bool = False,
    log: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Run (or resume) a bench and write its report into ``out_dir``; returns the report's content.

    Args:
        cfg: what to run.
        out_dir: the bench's folder (report, cached window errors, planner cells).
        backend: how the planner cells run: ``local`` (a process pool) or ``ray`` (:func:`agents.ablation.run_grid`).
        workers: planner cells at a time (default: the grid's rule).
        address: a Ray cluster's address (default: a local Ray instance).
        command: the command line recorded in the report.
        force: replace a report in ``out_dir`` that holds more (other splits, scenes or predictor, planner cells).
        log: called with one line of progress text at a time.

    Raises:
        ValueError: bad settings (unknown split, scene, predictor; episodes < 1).
        RuntimeError: a planner cell failed.
    """
    from crowdnav_mesrnn.data.constants import check_split
    from crowdnav_mesrnn.predictors import resolve
    from crowdnav_mesrnn.utils import code_version

    spec = resolve(cfg.predictor)
    for s in (*cfg.splits, *cfg.scenes):
        check_split(s)
    if cfg.episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {cfg.episodes}")
    out = Path(out_dir)
    if not force:
        _check_not_less(cfg, out / "report.json")
    grid = None
    if cfg.planner and cfg.scenes:  # built first: a bad setting fails before any work
        grid = bench_grid(cfg.predictor, out, cfg.scenes, cfg.episodes, cfg.seed, cfg.noisy_oracle_ade_m)
    started = time.perf_counter()
    report: dict[str, Any] = {
        "predictor": cfg.predictor,
        "spec": asdict(spec),
        "config": asdict(cfg),
        "command": command or f"crowdnav-mesrnn bench {cfg.predictor}",
        "code_version": code_version(),
        "episodes": cfg.episodes,
    }
    if cfg.splits:
        log(f"forecast accuracy of {cfg.predictor} on {', '.join(cfg.splits)}")
        report["predictor_metrics"] = predictor_metrics(
            cfg.predictor, cfg.splits, out / "windows", None, cfg.block_len, cfg.resamples, 0, log
        )
    if grid is not None:
        counts = run_planner_cells(grid, backend, workers, address, log)
        report["planner"] = planner_results(grid, cfg.predictor)
        report["planner"]["cells"] = {"ran": counts["ran"], "skipped": counts["skipped"]}
    report["seconds"] = round(time.perf_counter() - started, 1)
    write_report(report, out)
    return report


def _check_not_less(cfg: BenchConfig, path: Path) -> None:
    """Refuse to replace a report that holds data this run would not (a subset run into the same folder)."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    held = old.get("config") or {}
    lost = []
    if old.get("predictor") != cfg.predictor:
        lost.append(f"predictor {old.get('predictor')!r}")
    if set(held.get("splits") or ()) - set(cfg.splits):
        lost.append(f"splits {sorted(set(held['splits']) - set(cfg.splits))}")
    if old.get("planner") and not (cfg.planner and set(held.get("scenes") or ()) <= set(cfg.scenes)):
        lost.append("planner cells" if not cfg.planner else f"scenes {sorted(set(held['scenes']) - set(cfg.scenes))}")
    if lost:
        raise ConfigError(
            f"{path} holds {', '.join(lost)} that this run would drop; choose another --out, or pass --force"
        )


# ---------------------------------------------------------------------------- command line


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "bench",
        help="benchmark any predictor: ADE/FDE against CV, and the planner cells of the ablation, on one page",
        description=(
            "Scores PREDICTOR (a shipped model, an installed plug-in or package.module:Factory) on the ETH/UCY test "
            "windows against constant velocity, runs the sampling planner with its forecasts on held-out scenes "
            "against cv, oracle and a noisy-oracle sweep on the same episodes, and writes report.md, report.json "
            "and success_vs_ade.png into --out. Resumable: finished parts are reused."
        ),
    )
    p.add_argument("predictor", metavar="PREDICTOR", help="predictor name or import path package.module:Factory")
    p.add_argument(
        "--splits", nargs="+", default=list(SPLITS), choices=SPLITS, help="test windows of these splits (default: all)"
    )
    p.add_argument(
        "--scenes",
        nargs="+",
        default=list(DEFAULT_SCENES),
        choices=SPLITS,
        help=f"held-out scenes of the planner cells (default: {' '.join(DEFAULT_SCENES)}, as in the ablation)",
    )
    p.add_argument("--episodes", type=int, default=500, help="episodes per planner cell (default: 500)")
    p.add_argument("--seed", type=int, default=0, help="which seeded list of episodes (default: 0)")
    p.add_argument("--out", default=None, help="output folder (default: runs/bench/PREDICTOR)")
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--no-planner", action="store_true", help="forecast accuracy only (no planner cells)")
    p.add_argument(
        "--force", action="store_true", help="replace a report in --out holding more (other splits, scenes, cells)"
    )
    p.add_argument(
        "--backend", default="local", choices=("local", "ray"), help="how planner cells run (default: local pool)"
    )
    p.add_argument("--workers", type=int, default=None, help="planner cells at a time (default: the ablation's rule)")
    p.add_argument("--address", default=None, help="Ray cluster address HOST:PORT (--backend ray; default: local)")
    p.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples (default: 10000)")
    p.add_argument(
        "--block-len",
        type=int,
        default=DEFAULT_BLOCK_LEN,
        help=f"bootstrap block, windows (default: {DEFAULT_BLOCK_LEN})",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = BenchConfig(
        predictor=args.predictor,
        splits=tuple(args.splits),
        scenes=tuple(args.scenes),
        episodes=args.episodes,
        seed=args.seed,
        planner=not args.no_planner,
        block_len=args.block_len,
        resamples=args.resamples,
    )
    out = Path(args.out) if args.out else default_out(args.predictor)
    command = "crowdnav-mesrnn " + shlex.join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else ""
    run_bench(
        cfg,
        out,
        backend=args.backend,
        workers=args.workers,
        address=args.address,
        command=command,
        force=args.force,
        log=lambda m: print(m, flush=True),
    )
    print(f"report: {out / 'report.md'} (+ report.json{', success_vs_ade.png' if cfg.planner else ''})")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.bench``: the same as ``crowdnav-mesrnn bench``."""
    from crowdnav_mesrnn.cli import main as cli_main

    return cli_main(["bench", *(sys.argv[1:] if argv is None else argv)])
