"""A run's SB3 logger: ``progress.csv`` written atomically, and TensorBoard under ``tb/`` when installed."""

from __future__ import annotations

import csv
import importlib.util
import io
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.logger import KVWriter, Logger, TensorBoardOutputFormat, filter_excluded_keys

from crowdnav_mesrnn.utils import atomic_write_text


def csv_text(keys: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> str:
    """CSV text of ``rows`` with the columns ``keys`` (keys outside them are left out)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(keys), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, Any]]]:
    if not path.is_file():
        return [], []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or []), list(reader)


def _steps_of(row: Mapping[str, Any], key: str) -> float:
    try:
        return float(row.get(key) or 0)
    except ValueError:
        return 0.0


class ProgressCSV(KVWriter):
    """SB3 logger output writing ``progress.csv`` atomically (the whole file each time, new keys as new
    columns); on resume it keeps the rows logged up to the checkpoint."""

    def __init__(self, path: Path, keep_until_step: int | None = None) -> None:
        self.path = path
        self.keys, rows = _read_csv(path)
        if keep_until_step is None:
            rows = []
            self.keys = []
        self.rows = [r for r in rows if _steps_of(r, "time/total_timesteps") <= (keep_until_step or 0)]

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        values = filter_excluded_keys(key_values, key_excluded, "csv")
        row = {k: v for k, v in values.items() if isinstance(v, int | float | str | np.number)}
        self.keys.extend(k for k in row if k not in self.keys)
        self.rows.append(row)
        atomic_write_text(self.path, csv_text(self.keys, self.rows))

    def close(self) -> None:
        pass


#: The note that TensorBoard logs are not written was shown in this process (it is shown once).
_TB_NOTICE_SHOWN = False


def make_logger(run_dir: Path, keep_until_step: int | None) -> Any:
    """SB3 logger: ``progress.csv`` and, when tensorboard is installed, TensorBoard under ``tb/`` (without it, one
    warning per process says the logs are not written and how to get them)."""
    global _TB_NOTICE_SHOWN
    formats: list[Any] = [ProgressCSV(run_dir / "progress.csv", keep_until_step)]
    if importlib.util.find_spec("tensorboard") is not None:
        formats.append(TensorBoardOutputFormat(str(run_dir / "tb")))
    elif not _TB_NOTICE_SHOWN:
        _TB_NOTICE_SHOWN = True
        warnings.warn(
            "TensorBoard logs (tb/ in the run folder) are not written: tensorboard is not installed; "
            "pip install 'crowdnav-mesrnn[tb]' to get them (progress.csv is written either way)",
            UserWarning,
            stacklevel=2,
        )
    return Logger(str(run_dir), formats)
