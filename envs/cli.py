"""The environment's subcommands of ``crowdnav-mesrnn``: ``forecasts build`` and ``forecasts info``.

:func:`add_forecasts` is named in :data:`crowdnav_mesrnn.cli.COMMANDS` and imported only when the
subcommand runs.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_HELP
from envs.config import FORECAST_MEMORIES


def _build(args: argparse.Namespace) -> int:
    import sys

    from envs.forecasting.build import build_forecast_cache, check_cacheable
    from envs.forecasting.threads import FORECAST_THREADS

    check_cacheable(args.predictor)  # a name without a cache is refused before torch is imported

    if args.threads is not None and args.threads != FORECAST_THREADS:
        print(
            f"forecasts build: --threads {args.threads} is ignored: forecasts are computed on {FORECAST_THREADS} torch "
            "thread(s), the bits every environment computes (more threads change the last bits)",
            file=sys.stderr,
        )
    summary = build_forecast_cache(
        args.predictor,
        args.split,
        args.part,
        memory=args.memory,
        data_dir=args.data_dir,
        cache_dir=args.cache_dir,
        progress=not args.no_progress,
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"{summary['predictor']} ({summary['memory']}) forecasts of {len(summary['recordings'])} recording(s): "
            f"{summary['chunks']} chunks, {summary['loaded']} already cached, {summary['computed']} computed, "
            f"in {summary['seconds']:.1f} s -> {summary['cache_dir']}"
        )
    return 0


def _info(args: argparse.Namespace) -> int:
    from envs.forecasting.cache import cache_root, describe

    rows = describe(args.cache_dir)
    if args.json:
        print(json.dumps({"cache_dir": str(cache_root(args.cache_dir)), "entries": rows}, indent=2))
        return 0
    print(f"forecast cache: {cache_root(args.cache_dir)}")
    if not rows:
        print("  (empty)")
        return 0
    print(f"  {'source':<16}{'recording':<16}{'key':<22}{'chunks':>7}{'MB':>9}")
    for row in rows:
        print(
            f"  {row['source']:<16}{row['recording']:<16}{row['key']:<22}{row['chunks']:>7}{row['bytes'] / 1e6:>9.2f}"
        )
    total = sum(r["bytes"] for r in rows)
    print(f"  {len(rows)} entries, {sum(r['chunks'] for r in rows)} chunk files, {total / 1e6:.2f} MB")
    return 0


def add_forecasts(sub: Any) -> None:
    p = sub.add_parser(
        "forecasts",
        help="build and inspect the shared on-disk forecast cache",
        description=(
            "Learned forecasts depend only on (weights, recording, settings): they are computed once, stored in "
            "$CROWDNAV_MESRNN_CACHE (default ~/.cache/crowdnav-mesrnn/forecasts) and loaded by every process."
        ),
    )
    fsub = p.add_subparsers(dest="forecasts_cmd", required=True)
    b = fsub.add_parser("build", help="compute and store the forecasts of a split's recordings ahead of training")
    b.add_argument(
        "--predictor",
        required=True,
        metavar="PREDICTOR",
        help=f"{', '.join(predictors.names(predictors.PRETRAINED, plugins=False))}, an installed predictor plug-in or "
        "an import path package.module:Factory",
    )
    b.add_argument("--split", default=None, choices=SPLITS, help="default: every replayable recording")
    b.add_argument("--part", default="all", choices=("train", "test", "all"), help="default: all")
    b.add_argument("--memory", default="window", choices=FORECAST_MEMORIES, help="forecast memory (default: window)")
    b.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    b.add_argument("--cache-dir", default=None, help="cache folder (default: $CROWDNAV_MESRNN_CACHE, ...)")
    b.add_argument(
        "--threads", type=int, default=None, help="ignored: forecasts are computed on one torch thread (bit-exact)"
    )
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    b.add_argument("--json", action="store_true", help="print the summary as JSON")
    b.set_defaults(func=_build)
    i = fsub.add_parser("info", help="what is cached: entries per predictor and recording, sizes")
    i.add_argument("--cache-dir", default=None, help="cache folder (default: $CROWDNAV_MESRNN_CACHE, ...)")
    i.add_argument("--json", action="store_true", help="print one JSON object")
    i.set_defaults(func=_info)
