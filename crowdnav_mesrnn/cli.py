"""The ``crowdnav-mesrnn`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from typing import Any

Handler = Callable[[argparse.Namespace], int]
_SUBCOMMAND_BUILDERS: list[Callable[[Any], None]] = []


def subcommand(builder: Callable[[Any], None]) -> Callable[[Any], None]:
    """Register a function that adds a sub-parser (called with the top-level ``subparsers``)."""
    _SUBCOMMAND_BUILDERS.append(builder)
    return builder


# ---------------------------------------------------------------------------- data


def _data_summary(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.data.summary import data_summary, format_summary

    summary = data_summary(args.data_dir)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def _data_check(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.data.checks import check_data_dir

    report = check_data_dir(args.dir)
    for problem in report.problems:
        print(problem, file=sys.stderr)
    sums = "checksums verified against SHA256SUMS" if report.checksum_file else "no SHA256SUMS found"
    status = "OK" if report.ok else f"{len(report.problems)} problem(s)"
    print(f"{args.dir}: {report.checked} data files parsed, {sums}: {status}")
    return 0 if report.ok else 1


@subcommand
def _add_data(sub: Any) -> None:
    p = sub.add_parser("data", help="inspect and verify the ETH/UCY data")
    dsub = p.add_subparsers(dest="data_cmd", required=True)
    s = dsub.add_parser("summary", help="frames, pedestrians, step time and window counts")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--data-dir", default=None, help="data folder (default: $CROWDNAV_MESRNN_DATA, ...)")
    s.set_defaults(func=_data_summary)
    c = dsub.add_parser("check", help="verify SHA256SUMS and the format of every file in DIR")
    c.add_argument("dir")
    c.set_defaults(func=_data_check)


def build_parser() -> argparse.ArgumentParser:
    from crowdnav_mesrnn import __version__

    # Sub-commands of other modules register themselves on import.
    for mod in ("crowdnav_mesrnn.cli_predictor", "crowdnav_mesrnn.cli_env", "agents.cli"):
        try:
            __import__(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise
    parser = argparse.ArgumentParser(
        prog="crowdnav-mesrnn", description="MESRNN trajectory prediction and robot crowd navigation on ETH/UCY."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for builder in _SUBCOMMAND_BUILDERS:
        builder(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from crowdnav_mesrnn.config import ConfigError
    from crowdnav_mesrnn.data.paths import DataNotFoundError
    from crowdnav_mesrnn.data.recordings import DataFormatError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (DataNotFoundError, DataFormatError, ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"crowdnav-mesrnn: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crowdnav-mesrnn: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
