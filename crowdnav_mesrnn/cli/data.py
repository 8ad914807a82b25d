"""``crowdnav-mesrnn data ...``: download, inspect and verify the ETH/UCY data."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def _data_summary(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.data.summary import data_summary, format_summary

    summary = data_summary(args.data_dir)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def _data_check(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.data.checks import check_data_dir
    from crowdnav_mesrnn.data.paths import find_data_dir

    given = args.dir or args.data_dir
    root = Path(given) if given else find_data_dir()  # no folder given: the one the project would use
    report = check_data_dir(root)
    for problem in report.problems:
        print(problem, file=sys.stderr)
    sums = "checksums verified against SHA256SUMS" if report.checksum_file else "no SHA256SUMS found"
    status = "OK" if report.ok else f"{len(report.problems)} problem(s)"
    print(f"{root}: {report.checked} data files parsed, {sums}: {status}")
    return 0 if report.ok else 1


def _data_download(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.data.download import DownloadError, download_data, where_hint

    try:
        result = download_data(
            args.dest,
            args.url,
            timeout_s=args.timeout,
            deadline_s=args.deadline,
            force=args.force,
            progress=lambda m: print(m, flush=True),
        )
    except DownloadError as exc:
        print(f"crowdnav-mesrnn: error: {exc}", file=sys.stderr)
        return 1
    what = "already holds" if result.already_present else "now holds"
    print(f"{result.dest} {what} the ETH/UCY recordings ({result.files} files, SHA-256 verified).")
    print(where_hint(result.dest, result.found_by_default))
    print(f"Check it any time with `crowdnav-mesrnn data check {result.dest}`.")
    return 0


def add_parser(sub: Any) -> None:
    from crowdnav_mesrnn.data.download import DEFAULT_DEADLINE_S, DEFAULT_DEST, DEFAULT_TIMEOUT_S, seconds_option
    from crowdnav_mesrnn.data.paths import DATA_DIR_HELP

    p = sub.add_parser("data", help="download, inspect and verify the ETH/UCY data")
    dsub = p.add_subparsers(dest="data_cmd", required=True)
    s = dsub.add_parser("summary", help="frames, pedestrians, step time and window counts")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    s.set_defaults(func=_data_summary)
    c = dsub.add_parser("check", help="verify SHA256SUMS and the format of every file in a data folder")
    c.add_argument("dir", nargs="?", default=None, help="data folder (default: the one the project would use)")
    c.add_argument("--data-dir", default=None, help=f"same as DIR; {DATA_DIR_HELP}")
    c.set_defaults(func=_data_check)
    d = dsub.add_parser(
        "download",
        help="fetch the ETH/UCY recordings, verify them against pinned SHA-256 sums and install them atomically",
    )
    d.add_argument(
        "--dest",
        default=None,
        help=f"folder to create (default: {DEFAULT_DEST}, searched by the project; without --dest, a folder the "
        "project already uses instead ($CROWDNAV_MESRNN_DATA or ./data/eth_ucy) is kept when it verifies and "
        "refused when it does not)",
    )
    d.add_argument(
        "--url",
        default=None,
        help="a .zip in the Social-GAN datasets layout, or a base URL serving the project's layout "
        "(BASE/all_data/biwi_eth.txt, BASE/train/..., BASE/val/...); http(s)://, file:// or a local path; "
        "default: the Social-GAN datasets archive",
    )
    d.add_argument(
        "--timeout",
        type=seconds_option,
        default=DEFAULT_TIMEOUT_S,
        help=f"seconds a connection or read may stall before failing (default: {DEFAULT_TIMEOUT_S:g})",
    )
    d.add_argument(
        "--deadline",
        type=seconds_option,
        default=DEFAULT_DEADLINE_S,
        help="seconds the whole download may take, however slowly the server sends "
        f"(default: {DEFAULT_DEADLINE_S:g} = {DEFAULT_DEADLINE_S / 60:g} min)",
    )
    d.add_argument(
        "--force",
        action="store_true",
        help="in an existing --dest that does not verify, replace the project's files (the pinned recordings and "
        "SHA256SUMS); nothing else in it is touched",
    )
    d.set_defaults(func=_data_download)
