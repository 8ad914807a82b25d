""":func:`run_bench`: one predictor's bench (forecast accuracy, then the planner cells) into a folder, resumably."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from agents.bench.metrics import predictor_metrics
from agents.bench.planner import (
    DEFAULT_SCENES,
    NOISY_ORACLE_ADE_M,
    bench_grid,
    planner_results,
    run_planner_cells,
)
from agents.bench.report import write_report
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.evaluation.statistics import DEFAULT_BLOCK_LEN


@dataclass(frozen=True)
class BenchConfig:
    """What one bench runs."""

    predictor: str
    """Predictor name (shipped, installed plug-in) or import path ``package.module:Factory``."""
    splits: tuple[str, ...] = SPLITS
    """Leave-one-out splits whose test windows are scored (ADE/FDE)."""
    scenes: tuple[str, ...] = DEFAULT_SCENES
    """Held-out scenes (splits) of the planner cells."""
    episodes: int = 500
    """Seeded episodes per planner cell (the ablation uses 500)."""
    seed: int = 0
    """Which seeded list of episodes."""
    noisy_oracle_ade_m: tuple[float, ...] = NOISY_ORACLE_ADE_M
    """Target ADEs of the noisy-oracle reference arms, metres."""
    planner: bool = True
    """Run the planner cells (False: forecast accuracy only)."""
    block_len: int = DEFAULT_BLOCK_LEN
    """Moving-block length of the bootstrap, windows."""
    resamples: int = 10_000
    """Bootstrap resamples."""


def default_out(predictor: str) -> Path:
    """``runs/bench/<predictor>`` (an import path's ``:`` and ``.`` made file-name safe)."""
    return Path("runs") / "bench" / predictor.replace(":", "_").replace("/", "_")


def run_bench(
    cfg: BenchConfig,
    out_dir: str | Path,
    *,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    command: str = "",
    force: bool = False,
    log: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Run (or resume) a bench and write its report into ``out_dir``; returns the report's content.

    Args:
        cfg: what to run.
        out_dir: the bench's folder (report, cached window errors, planner cells).
        backend: how the planner cells run: ``local`` (a process pool) or ``ray`` (:func:`agents.ablation.run_grid`).
        workers: planner cells at a time (default: the grid's rule).
        address: a Ray cluster's address (default: a local Ray instance).
        command: the command line recorded in the report.
        force: replace a report in ``out_dir`` that holds more (other splits, scenes or predictor, planner cells).
        log: called with one line of progress text at a time.

    Raises:
        ValueError: bad settings (unknown split, scene, predictor; episodes < 1).
        RuntimeError: a planner cell failed.
    """
    from crowdnav_mesrnn.data.constants import check_split
    from crowdnav_mesrnn.predictors import resolve
    from crowdnav_mesrnn.utils import code_version

    spec = resolve(cfg.predictor)
    for s in (*cfg.splits, *cfg.scenes):
        check_split(s)
    if cfg.episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {cfg.episodes}")
    out = Path(out_dir)
    if not force:
        _check_not_less(cfg, out / "report.json")
    grid = None
    if cfg.planner and cfg.scenes:  # built first: a bad setting fails before any work
        grid = bench_grid(cfg.predictor, out, cfg.scenes, cfg.episodes, cfg.seed, cfg.noisy_oracle_ade_m)
    started = time.perf_counter()
    report: dict[str, Any] = {
        "predictor": cfg.predictor,
        "spec": asdict(spec),
        "config": asdict(cfg),
        "command": command or f"crowdnav-mesrnn bench {cfg.predictor}",
        "code_version": code_version(),
        "episodes": cfg.episodes,
    }
    if cfg.splits:
        log(f"forecast accuracy of {cfg.predictor} on {', '.join(cfg.splits)}")
        report["predictor_metrics"] = predictor_metrics(
            cfg.predictor, cfg.splits, out / "windows", None, cfg.block_len, cfg.resamples, 0, log
        )
    if grid is not None:
        counts = run_planner_cells(grid, backend, workers, address, log)
        report["planner"] = planner_results(grid, cfg.predictor)
        report["planner"]["cells"] = {"ran": counts["ran"], "skipped": counts["skipped"]}
    report["seconds"] = round(time.perf_counter() - started, 1)
    write_report(report, out)
    return report


def _check_not_less(cfg: BenchConfig, path: Path) -> None:
    """Refuse to replace a report that holds data this run would not (a subset run into the same folder)."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    held = old.get("config") or {}
    lost = []
    if old.get("predictor") != cfg.predictor:
        lost.append(f"predictor {old.get('predictor')!r}")
    if set(held.get("splits") or ()) - set(cfg.splits):
        lost.append(f"splits {sorted(set(held['splits']) - set(cfg.splits))}")
    if old.get("planner") and not (cfg.planner and set(held.get("scenes") or ()) <= set(cfg.scenes)):
        lost.append("planner cells" if not cfg.planner else f"scenes {sorted(set(held['scenes']) - set(cfg.scenes))}")
    if lost:
        raise ConfigError(
            f"{path} holds {', '.join(lost)} that this run would drop; choose another --out, or pass --force"
        )
