"""Verifying a data folder: checksums against ``SHA256SUMS`` and the format of every file."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

from crowdnav_mesrnn.data.recordings import DataFormatError, parse_file


@dataclass
class CheckReport:
    """Outcome of :func:`check_data_dir`; ``ok`` when no problem was found."""

    checked: int = 0
    checksum_file: bool = False
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_data_dir(root: str | os.PathLike[str]) -> CheckReport:
    """Verify every listed checksum (when ``SHA256SUMS`` exists) and parse every ``.txt`` file; a folder without any
    data file (``.txt``) is a problem (a check must not pass on an empty or wrong folder)."""
    root = Path(root)
    report = CheckReport()
    if not root.is_dir():
        report.problems.append(f"{root}: not a directory")
        return report
    sums = root / "SHA256SUMS"
    if sums.is_file():
        report.checksum_file = True
        for lineno, line in enumerate(sums.read_text().splitlines(), start=1):
            if not line.strip():
                continue
            parts = line.split(maxsplit=1)
            if len(parts) != 2:
                report.problems.append(f"{sums}:{lineno}: malformed checksum line {line!r}")
                continue
            digest, rel = parts[0], parts[1].lstrip("*").strip()
            target = root / rel
            if not target.is_file():
                report.problems.append(f"{target}: listed in SHA256SUMS but missing")
            elif sha256_file(target) != digest.lower():
                report.problems.append(f"{target}: checksum mismatch")
    for path in sorted(root.rglob("*.txt")):
        report.checked += 1
        try:
            parse_file(path)
        except DataFormatError as exc:
            report.problems.append(str(exc))
    if report.checked == 0:
        report.problems.append(
            f"{root}: no data files (*.txt) found: not an ETH/UCY folder (expected all_data/, train/, val/ of the "
            "SGAN copy)"
        )
    return report
