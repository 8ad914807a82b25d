"""The command line of the bench: ``crowdnav-mesrnn bench`` and ``python -m agents.bench``."""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from agents.bench.planner import DEFAULT_SCENES
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP
from crowdnav_mesrnn.evaluation.statistics import DEFAULT_BLOCK_LEN


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
    predictors.check(args.predictor)  # a mistyped name is refused before torch is imported
    from agents.bench.run import BenchConfig, default_out, run_bench

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
