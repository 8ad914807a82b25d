"""Move results folders' older single ``episodes.csv.gz`` into the per-policy archive, row for row.

``python -m agents.ablation.split_archive FOLDER [FOLDER ...]``

For results whose summary cannot be rendered again from them (an archive too old for a re-render, which
``--summarize-only`` keeps as it is): each folder's ``episodes.csv.gz`` becomes ``episodes/<policy>.csv.gz``, header and
values unchanged, and is removed once the new files read back its rows exactly
(:func:`agents.ablation.archive.split_legacy`). Other results need not be moved: ``--summarize-only`` moves their
archive when it re-renders them, and every reader reads either layout.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from agents.ablation.archive import ARCHIVE_DIR, LEGACY_ARCHIVE, split_legacy


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("folders", nargs="+", help="results folders holding an episodes.csv.gz, e.g. results/ablation/x")


def run_from_args(args: argparse.Namespace) -> int:
    for folder in args.folders:
        if not (Path(folder) / LEGACY_ARCHIVE).exists() and (Path(folder) / ARCHIVE_DIR).is_dir():
            print(f"{Path(folder) / ARCHIVE_DIR}/: split already (no {LEGACY_ARCHIVE}); left as it is")
            continue
        files = split_legacy(folder)
        largest = max(files, key=lambda name: len(files[name]), default="")
        print(
            f"{Path(folder) / ARCHIVE_DIR}/: {len(files)} file(s)"
            + (f", the largest {largest} ({len(files[largest]) / 2**20:.2f} MiB)" if largest else "")
        )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from agents.entry import module_main

    return module_main("python -m agents.ablation.split_archive", __doc__, add_arguments, run_from_args, argv)


if __name__ == "__main__":
    sys.exit(main())
