"""Reading the evaluation cells' episodes, pooled per (policy, arm), and the grid's episode archive (its content; its
files on disk: :mod:`agents.ablation.archive`)."""

from __future__ import annotations

import csv
import datetime
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from agents.ablation.archive import archive_files
from agents.ablation.cells import CellStatus


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
    """The evaluation's own aggregates (:func:`agents.evaluation.summary.summarise`) of the pooled episodes: rates with
    Wilson intervals, metric means with bootstrap intervals (navigation time and path ratio over successful
    episodes; the forecast ADE is undefined in the ``none`` arm).

    Episodes pooled from cells that record the metrics added later (:data:`agents.rollout.ADDED_METRICS`) and cells
    whose episodes were written before them (a cell reused from an older grid's archive) leave those metrics' means
    and intervals ``None`` (their ``_n`` stays the count of episodes recording them) and name them in
    ``metrics_partly_recorded``: averaging the cells that have them would pass a subset of splits for the whole."""
    from agents.evaluation.summary import summarise

    out = summarise(episodes.rows)
    partial = [m for m in partly_recorded(episodes) if f"{m}_mean" in out]
    for metric in partial:
        out[f"{metric}_mean"] = None
        out[f"{metric}_ci"] = None
    if partial:
        out["metrics_partly_recorded"] = partial
    return out


#: ``intervals`` of an aggregate whose intervals resample episodes (:func:`episode_intervals`).
EPISODE_BOOTSTRAP: Final[str] = "percentile bootstrap over episodes (an episode's seeds resampled together)"


def episode_clusters(keys: Sequence[tuple[str, int | None, int]]) -> tuple[np.ndarray, int]:
    """``(which, n)``: for each key (split, seed, episode) the index of its episode (split, episode) among the ``n``
    distinct ones, numbered in order of first appearance."""
    clusters: dict[tuple[str, int], int] = {}
    which = np.asarray([clusters.setdefault((split, ep), len(clusters)) for split, _, ep in keys], dtype=int)
    return which, len(clusters)


def resample_weights(n: int, n_resamples: int = 2000, seed: int = 0) -> np.ndarray:
    """``(n_resamples, n)``: how often each of ``n`` clusters is drawn in each bootstrap resample (seeded)."""
    rng = np.random.default_rng(seed)
    return rng.multinomial(n, np.full(n, 1.0 / n), size=n_resamples).astype(float)


def _ratio_interval(sums: np.ndarray, counts: np.ndarray, weights: np.ndarray, confidence: float) -> list[float] | None:
    """Percentile bootstrap interval of ``sum(sums) / sum(counts)`` over the resamples of the clusters (the entries)
    that ``weights`` (:func:`resample_weights`) draws; ``None`` when no cluster counts anything. Resamples whose
    clusters count nothing are left out."""
    if counts.sum() <= 0:
        return None
    num, den = weights @ sums, weights @ counts
    ratios = num[den > 0] / den[den > 0]
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(ratios, [alpha, 1.0 - alpha])
    return [float(lo), float(hi)]


def episode_intervals(
    episodes: _Episodes, out: Mapping[str, Any], confidence: float = 0.95, n_resamples: int = 2000, seed: int = 0
) -> dict[str, Any]:
    """``out`` (:func:`aggregate` of ``episodes``) with every rate's and mean's interval replaced by a percentile
    bootstrap that resamples episodes -- (split, episode index), each with all its training seeds' rows -- instead of
    rows (``test_unit: episode``).

    A learned policy's seeds replay the same episodes, and an episode hard for one seed tends to be hard for the others,
    so its rows are not independent: Wilson's interval over the pooled rows, and a bootstrap over rows, are too narrow
    (in the learned grid about half as wide as this one). Each estimate stays the pooled rows' (a ratio of sums: the
    rate is successes / rows; a mean, the sum of the values the metric is defined for / their number) and so does
    each ``_n``; the interval is the percentile interval of that ratio over ``n_resamples`` resamples of the episodes
    (seeded, so a summary re-renders identically). ``intervals`` names the method. Intervals ``None`` in ``out`` (a
    metric partly recorded, none defined) stay ``None``."""
    from agents.evaluation.summary import OUTCOMES as EVAL_OUTCOMES
    from agents.evaluation.summary import SUCCESS_ONLY_METRICS

    res = dict(out)
    which, n_clusters = episode_clusters(episodes.keys)
    if n_clusters == 0:
        return res
    weights = resample_weights(n_clusters, n_resamples, seed)  # one set of resamples for every estimate
    outcome = episodes.outcome()
    rows = np.bincount(which, minlength=n_clusters).astype(float)
    for name in EVAL_OUTCOMES:
        if res.get(f"{name}_ci") is not None:
            hits = np.bincount(which, weights=(outcome == name).astype(float), minlength=n_clusters)
            res[f"{name}_ci"] = _ratio_interval(hits, rows, weights, confidence)
    success = outcome == "success"
    for key in [k for k in out if k.endswith("_ci") and k[: -len("_ci")] not in EVAL_OUTCOMES]:
        metric = key[: -len("_ci")]
        if res[key] is None:
            continue
        values = episodes.metric(metric)
        use = np.isfinite(values) & (success if metric in SUCCESS_ONLY_METRICS else True)
        sums = np.bincount(which[use], weights=values[use], minlength=n_clusters)
        counts = np.bincount(which[use], minlength=n_clusters).astype(float)
        res[key] = _ratio_interval(sums, counts, weights, confidence)
    res["intervals"] = EPISODE_BOOTSTRAP
    return res


def partly_recorded(episodes: _Episodes) -> tuple[str, ...]:
    """:data:`agents.rollout.ADDED_METRICS` when some of ``episodes``' cells (split, seed) record them and others do
    not (every row blank or without the column), else ``()``. ``spl``, defined for every episode of a cell that
    records the added metrics, tells the two apart."""
    from agents.rollout import ADDED_METRICS

    recorded: dict[tuple[str, int | None], bool] = {}
    for (split, seed, _), row in zip(episodes.keys, episodes.rows, strict=True):
        has = bool(str(row.get("spl") or "").strip())
        recorded[(split, seed)] = recorded.get((split, seed), False) or has
    return ADDED_METRICS if len(set(recorded.values())) == 2 else ()


def cell_info(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """What the summary says of the cells, from their ``cells.json`` records (:func:`cell_record`): which are
    missing (not done), the compute in done cells per kind, and the grid's span from the first attempt's start
    to the last attempt's end (``None`` when the records have no start times)."""
    missing: list[str] = []
    walls: dict[str, float] = {"train": 0.0, "eval": 0.0}
    starts: list[str] = []
    ends: list[str] = []
    for rec in records:
        for att in rec.get("attempts") or []:
            starts.append(att.get("started") or "")
            ends.append(att.get("finished") or "")
        if rec.get("state") != "done":
            missing.append(rec["cell"])
            continue
        walls[rec["cell"].split("/", 1)[0]] += float(rec.get("wall_s") or 0.0)
    first = min((w for w in map(_when, starts) if w), default=None)
    last = max((w for w in map(_when, ends) if w), default=None)
    return {
        "missing_cells": missing,
        "cell_wall_s": walls,
        "first_start": first.isoformat() if first else None,
        "last_finish": last.isoformat() if last else None,
        "span_s": (last - first).total_seconds() if first and last else None,
    }


def cell_record(st: CellStatus) -> dict[str, Any]:
    """One line of ``cells.json``: a cell's state, cost and provenance, with what :func:`cell_info` reads
    (every attempt's start and end) and what the cell's result depends on (its spec), so that the committed
    results alone can be summarised again (:mod:`agents.ablation.results`)."""
    meta = st.meta or {}
    rate = meta.get("steps_per_s") if st.cell.kind == "train" else meta.get("episodes_per_s")
    return {
        "cell": st.cell.name,
        "state": st.state,
        "wall_s": meta.get("wall_s"),
        "steps_per_s" if st.cell.kind == "train" else "episodes_per_s": None if rate is None else round(rate, 3),
        # cells that recorded their CPU time (absent in older records, so their cells.json stays as it was)
        **{k: round(meta[k], 3) for k in ("cpu_s", "steps_per_cpu_s", "episodes_per_cpu_s") if meta.get(k) is not None},
        "code_version": meta.get("code_version"),
        "finished": (meta.get("attempts") or [{}])[-1].get("finished"),
        "weights_sha256": {k: v[:12] for k, v in (meta.get("weights") or {}).items()},
        "model_sha256": (meta.get("model_sha256") or "")[:12] or None,
        "attempts": [{"started": a.get("started"), "finished": a.get("finished")} for a in meta.get("attempts", [])],
        "spec": meta.get("spec"),
    }


#: Leading columns of the results' episode archive (the cell and the episode), then every
#: per-episode metric of :data:`agents.rollout.METRICS` the episodes record (:func:`agents.rollout.recorded_metrics`).
ARCHIVE_KEYS: Final[tuple[str, ...]] = ("policy", "arm", "split", "seed", "episode", "outcome")
#: Per-episode counts archived after the metrics: pop-in events (a track that began on the robot, ``envs.popin``),
#: which the summary counts per cell (``popin_episodes``, ``popin_events``).
ARCHIVE_COUNTS: Final[tuple[str, ...]] = ("popin_events",)


def _has_disturbance(pooled: Mapping[tuple[str, str], _Episodes]) -> bool:
    """Whether any episode reports a disturbance metric (:data:`agents.rollout.DISTURBANCE_METRICS`)."""
    from agents.rollout import DISTURBANCE_METRICS

    return any(row.get(m) not in (None, "") for eps in pooled.values() for row in eps.rows for m in DISTURBANCE_METRICS)


def _exact(value: str | None) -> str:
    """A metric as the archive stores it: the shortest text that reads back as the same float ("" if undefined)."""
    x = _num(value)
    if not math.isfinite(x):
        return ""
    text = repr(x)
    return text[:-2] if text.endswith(".0") else text


def episodes_archive(pooled: Mapping[tuple[str, str], _Episodes]) -> dict[str, bytes]:
    """Every evaluated episode as the archive's files, ``{file name: gzipped CSV}``, one per policy
    (:mod:`agents.ablation.archive`), committed beside the summary in ``episodes/``. Each file holds
    :data:`ARCHIVE_KEYS` and the metrics, every value exactly as the evaluation wrote it, and is byte-identical for
    identical inputs. The summary is computed from these files (:func:`read_archive`), so the results alone reproduce
    it. Read in the order of their policies' names, the files hold the rows of the single ``episodes.csv.gz`` that
    this function wrote before, in the same order.

    The disturbance metrics (:data:`agents.rollout.DISTURBANCE_METRICS`) are the last columns when some episode
    reports them; an archive of episodes that do not (every grid before reacting pedestrians) has no such columns, so
    its rows are as before, and its episodes read them as absent (blank), never as zero."""
    from agents.rollout import DISTURBANCE_METRICS, recorded_metrics

    # the metrics the episodes record: one added since an archive was written stays out of it (agents.rollout)
    metrics = recorded_metrics([row for eps in pooled.values() for row in eps.rows])
    extra = (*ARCHIVE_COUNTS, *(DISTURBANCE_METRICS if _has_disturbance(pooled) else ()))
    rows: list[list[object]] = []
    for (policy, arm), eps in sorted(pooled.items()):
        for (split, seed, ep), row in sorted(
            zip(eps.keys, eps.rows, strict=True),
            key=lambda kr: (kr[0][0], -1 if kr[0][1] is None else kr[0][1], kr[0][2]),
        ):
            values = [_exact(row.get(col)) for col in (*metrics, *extra)]
            rows.append([policy, arm, split, "" if seed is None else seed, ep, row.get("outcome", ""), *values])
    return archive_files((*ARCHIVE_KEYS, *metrics, *extra), rows)


def archive_rows(rows: Iterable[Mapping[str, str]]) -> dict[str, list[dict[str, str]]]:
    """The archive's rows (:func:`agents.ablation.archive.read_rows`, :func:`agents.ablation.archive.files_rows`) per
    evaluation cell name (``eval/<split>/<policy>/<arm>[/seed<k>]``), each with ``episode``, ``outcome`` and the
    metrics."""
    out: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        name = f"eval/{row['split']}/{row['policy']}/{row['arm']}" + (f"/seed{row['seed']}" if row["seed"] else "")
        out.setdefault(name, []).append({k: v for k, v in row.items() if k not in ("policy", "arm", "split", "seed")})
    return out


def read_archive(rows: Iterable[Mapping[str, str]], splits: Sequence[str]) -> dict[tuple[str, str], _Episodes]:
    """The archive's rows (:func:`archive_rows`) as episodes pooled per (policy, arm), in the grid's order
    (``splits``' order, then training seed, then episode) -- the order in which the cells' own files list them."""
    pooled: dict[tuple[str, str], list[tuple[tuple[int, int, int], str, int | None, dict[str, str]]]] = {}
    for name, cell_rows in archive_rows(rows).items():
        _, split, policy, arm, *rest = name.split("/")
        seed = int(rest[0].removeprefix("seed")) if rest else None
        order = splits.index(split) if split in splits else len(splits)
        for row in cell_rows:
            ep = int(row["episode"])
            pooled.setdefault((policy, arm), []).append(((order, -1 if seed is None else seed, ep), split, seed, row))
    out: dict[tuple[str, str], _Episodes] = {}
    for key, items in pooled.items():
        items.sort(key=lambda item: item[0])
        out[key] = _Episodes([(sp, sd, o[2]) for o, sp, sd, _ in items], [row for *_, row in items])
    return out


def _when(stamp: str | None) -> datetime.datetime | None:
    try:
        return datetime.datetime.fromisoformat(stamp) if stamp else None
    except ValueError:
        return None
