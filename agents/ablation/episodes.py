"""Reading the evaluation cells' episodes, pooled per (policy, arm), and the combined episode archive."""

from __future__ import annotations

import csv
import datetime
import io
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from agents.ablation.cells import CellStatus, cell_dir, plan
from agents.ablation.config import AblationConfig


def read_episodes(path: str | os.PathLike[str]) -> list[dict[str, str]]:
    """Rows of an ``episodes.csv`` (empty if the file is missing)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            return list(csv.DictReader(fh))
    except FileNotFoundError:
        return []


def _num(value: str | None) -> float:
    try:
        return float(value) if value not in (None, "") else math.nan
    except ValueError:
        return math.nan


@dataclass
class _Episodes:
    """Evaluation episodes of one (policy, arm) pooled over cells: ``rows[i]`` (an ``episodes.csv`` row) is
    episode ``keys[i] = (split, training seed, episode index)``."""

    keys: list[tuple[str, int | None, int]] = field(default_factory=list)
    rows: list[Mapping[str, str]] = field(default_factory=list)

    def add(self, split: str, seed: int | None, rows: Sequence[Mapping[str, str]]) -> None:
        for i, row in enumerate(rows):
            self.keys.append((split, seed, int(_num(row.get("episode", str(i))))))
            self.rows.append(row)

    def subset(self, keep: Sequence[bool]) -> _Episodes:
        chosen = [i for i, b in enumerate(keep) if b]
        return _Episodes([self.keys[i] for i in chosen], [self.rows[i] for i in chosen])

    def outcome(self) -> np.ndarray:
        return np.asarray([str(r.get("outcome", "")) for r in self.rows], dtype=object)

    def metric(self, name: str) -> np.ndarray:
        return np.asarray([_num(r.get(name)) for r in self.rows], dtype=float)

    def __len__(self) -> int:
        return len(self.keys)


def aggregate(episodes: _Episodes) -> dict[str, Any]:
    """The evaluation's own aggregates (:func:`agents.evaluate.summarise`) of the pooled episodes: rates with
    Wilson intervals, metric means with bootstrap intervals (navigation time and path ratio over successful
    episodes; the forecast ADE is undefined in the ``none`` arm)."""
    from agents.evaluate import summarise

    return summarise(episodes.rows)


def _collect(cfg: AblationConfig) -> tuple[dict[tuple[str, str], _Episodes], dict[str, Any]]:
    """Episodes of every finished evaluation cell, keyed by (policy, arm); and which cells are missing."""
    pooled: dict[tuple[str, str], _Episodes] = {}
    missing: list[str] = []
    walls: dict[str, float] = {"train": 0.0, "eval": 0.0}
    starts: list[str] = []
    ends: list[str] = []
    statuses = plan(cfg)
    for st in statuses:
        if st.meta:
            for att in st.meta.get("attempts", []):
                starts.append(att.get("started", ""))
                ends.append(att.get("finished", ""))
        if st.state != "done":
            missing.append(st.cell.name)
            continue
        walls[st.cell.kind] += float((st.meta or {}).get("wall_s", 0.0))
        if st.cell.kind != "eval":
            continue
        rows = read_episodes(cell_dir(cfg, st.cell) / "episodes.csv")
        pooled.setdefault((st.cell.policy.name, st.cell.arm.label), _Episodes()).add(st.cell.split, st.cell.seed, rows)
    first = min((w for w in map(_when, starts) if w), default=None)
    last = max((w for w in map(_when, ends) if w), default=None)
    info = {
        "cells": [_cell_record(st) for st in statuses],
        "missing_cells": missing,
        "cell_wall_s": walls,
        "first_start": first.isoformat() if first else None,
        "last_finish": last.isoformat() if last else None,
        "span_s": (last - first).total_seconds() if first and last else None,
    }
    return pooled, info


def _cell_record(st: CellStatus) -> dict[str, Any]:
    """One line of ``cells.json``: a cell's state, cost and provenance."""
    meta = st.meta or {}
    rate = meta.get("steps_per_s") if st.cell.kind == "train" else meta.get("episodes_per_s")
    return {
        "cell": st.cell.name,
        "state": st.state,
        "wall_s": meta.get("wall_s"),
        "steps_per_s" if st.cell.kind == "train" else "episodes_per_s": None if rate is None else round(rate, 3),
        "code_version": meta.get("code_version"),
        "finished": (meta.get("attempts") or [{}])[-1].get("finished"),
        "weights_sha256": {k: v[:12] for k, v in (meta.get("weights") or {}).items()},
        "model_sha256": (meta.get("model_sha256") or "")[:12] or None,
    }


#: Leading columns of the results' combined ``episodes.csv.gz`` (the cell and the episode), then every
#: per-episode metric of :data:`agents.evaluate.METRICS`.
ARCHIVE_KEYS: Final[tuple[str, ...]] = ("policy", "arm", "split", "seed", "episode", "outcome")


def episodes_archive(pooled: Mapping[tuple[str, str], _Episodes]) -> bytes:
    """Every evaluated episode in one gzipped CSV (:data:`ARCHIVE_KEYS` and the metrics, 4 decimals;
    byte-identical for identical inputs), small enough to commit beside the summary so the tests can be
    redone without the runs."""
    import gzip

    from agents.evaluate import METRICS

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow((*ARCHIVE_KEYS, *METRICS))
    for (policy, arm), eps in sorted(pooled.items()):
        for (split, seed, ep), row in sorted(
            zip(eps.keys, eps.rows, strict=True), key=lambda kr: (kr[0][0], kr[0][1] or -1, kr[0][2])
        ):
            values = []
            for col in METRICS:
                x = _num(row.get(col))
                values.append("" if not math.isfinite(x) else f"{x:.4f}".rstrip("0").rstrip("."))
            writer.writerow([policy, arm, split, "" if seed is None else seed, ep, row.get("outcome", ""), *values])
    return gzip.compress(buf.getvalue().encode("utf-8"), mtime=0)


def _when(stamp: str | None) -> datetime.datetime | None:
    try:
        return datetime.datetime.fromisoformat(stamp) if stamp else None
    except ValueError:
        return None
