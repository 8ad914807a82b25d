"""The command line of the ablation: ``python -m agents.ablation`` and ``crowdnav-mesrnn ablation``."""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence

from agents.ablation.backends import replicate, run_grid
from agents.ablation.cells import default_workers, expand, select
from agents.ablation.config import BACKENDS, load_config
from agents.ablation.dryrun import dry_run
from agents.ablation.ray_backend import CONNECT_TIMEOUT_S
from agents.ablation.results import ResultsKept
from agents.ablation.summary import summarize
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP

EPILOG: str = f"""\
Ray (--backend ray): pip install 'crowdnav-mesrnn[ray]' (ray>=2.9; tested with Ray 2.60). The driver and
every node need the same Ray and Python versions, the project and its predictor weights, and the ETH/UCY
data at $CROWDNAV_MESRNN_DATA; no shared storage (files travel with the tasks, training checkpoints are
shipped back as they are written). On a cluster:
  CROWDNAV_MESRNN_DATA=/data/eth_ucy ray start --head --port 6379     # the head
  CROWDNAV_MESRNN_DATA=/data/eth_ucy ray start --address HEAD:6379    # every other node
  python -m agents.ablation CONFIG --backend ray --address HEAD:6379
--address is probed (TCP, {CONNECT_TIMEOUT_S:g} s) before any cell starts; a head that refuses the driver
(other Ray version, wrong token) is reported after Ray's own wait, about 20 s. Token authentication
(Ray >= 2.52): a head started while a token exists (~/.ray/auth_token, which Ray >= 2.59 creates for
any local instance, RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH) requires it; the driver turns it on the same way
and says so (RAY_AUTH_MODE=disabled: off); every other node needs the same token. Without --address a
local Ray instance is started and stopped.

Ctrl-C: the first lets the running cells finish, starts no other and names them; the second stops them
(a training run keeps its last checkpoint, taken at a round boundary, and resumes from it). Exit status:
0 done; 1 a cell failed or was skipped, or result files were kept; 2 bad input; 130 interrupted."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``python -m agents.ablation`` and ``crowdnav-mesrnn ablation`` (and the set-up of the
    Ray backend, Ctrl-C and the exit status in the help's epilog)."""
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    if p.description:
        p.description = textwrap.fill(p.description, 79)
    p.epilog = EPILOG
    p.add_argument("config", help="grid YAML, e.g. configs/ablation/planning_aid.yaml")
    p.add_argument("--dry-run", action="store_true", help="list every cell with its state and estimated time")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="cells at a time (default: cores // the largest cpus of a cell; 1 = in this process)",
    )
    p.add_argument("--backend", choices=BACKENDS, default="local", help="local process pool (default) or Ray tasks")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster address, HOST:6379 (the head's port) or ray://HOST:10001 (Ray Client); default: start a "
        "local Ray instance. See the set-up below",
    )
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--only", default=None, help="comma-separated globs of cell names, e.g. 'eval/zara1/planner/*'")
    p.add_argument(
        "--summarize-only",
        action="store_true",
        help="write summary.json/.md, cells.json, episodes/ and plots from finished cells (cells without a "
        "run folder are read from the committed results); leaves the files alone when nothing but the stamps "
        "would change, and refuses (exit 1) to replace them with a summary holding less",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the result files even with a summary holding fewer finished cells, or a re-render of an "
        "archive that differs from them",
    )
    p.add_argument(
        "--replicate",
        metavar="DIR",
        default=None,
        help="run the --only cells (and the training runs they need) afresh in scratch folder DIR and compare "
        "their evaluations with the grid's, episode by episode (a determinism and code-change check)",
    )


def run_from_args(args: argparse.Namespace) -> int:
    """Handler shared by both entry points; 1 when a cell failed."""
    cfg = load_config(args.config)
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    if args.address and args.backend != "ray":
        raise ConfigError("--address needs --backend ray")
    if args.replicate and (args.dry_run or args.summarize_only):
        raise ConfigError("--replicate cannot be combined with --dry-run or --summarize-only")
    if args.dry_run:
        cells = select(expand(cfg), args.only)
        dry_run(cfg, cells, args.workers or default_workers(cells))
        return 0
    if args.summarize_only:
        try:
            summarize(cfg, force=args.force)
        except ResultsKept as kept:
            print(f"crowdnav-mesrnn: {kept}", file=sys.stderr)
            return 1
        return 0
    if args.replicate:
        if not args.only:
            raise ConfigError("--replicate needs --only (the cells to replicate, e.g. 'eval/zara1/ppo/cv/seed1')")
        if args.backend != "local":
            raise ConfigError(f"--replicate runs on the local backend; got --backend {args.backend}")
        return 1 if replicate(cfg, args.only, args.replicate, args.workers) else 0
    result = run_grid(
        cfg, backend=args.backend, workers=args.workers, address=args.address, only=args.only, force=args.force
    )
    for name, error in result["failed"].items():
        print(f"failed: {name}\n{error}", file=sys.stderr)
    if result["interrupted"]:
        return 130
    return 1 if result["failed"] or result["skipped"] or result["summary"] == "kept" else 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.ablation ...`` is ``crowdnav-mesrnn ablation ...`` (same parser, same error handling)."""
    from crowdnav_mesrnn.cli import main as cli_main

    return cli_main(["ablation", *(sys.argv[1:] if argv is None else argv)])
