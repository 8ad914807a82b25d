"""The planner half of ``crowdnav-mesrnn bench``: the sampling planner on held-out scenes with the benchmarked
predictor's forecasts, against constant velocity, the true future (oracle) and the noisy-oracle sweep on the same
seeded episodes, with paired tests.

These are the planner cells of the planning-aid ablation (``configs/ablation/planning_aid.yaml``) with one more
forecast arm. A cell is one (scene, arm) evaluation (:class:`PlannerCell`); :func:`run_cells` runs the cells that
are not done yet through a runner (:data:`CellRunner`): the local one evaluates them one after another in this
process. Each cell is a folder holding ``episodes.csv``, ``summary.json`` and ``cell.json`` (its key); a cell whose
``cell.json`` matches is skipped, so an interrupted bench resumes where it stopped and a re-run recomputes nothing.
The cells' key holds the predictor's fingerprint (weights, or a plug-in's identity), the episode count and seed.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agents.stats import holm, mcnemar_exact, wilson_interval
from crowdnav_mesrnn.utils import atomic_write_json

#: Held-out scenes of the planning-aid ablation (its planner cells).
DEFAULT_SCENES: tuple[str, ...] = ("univ", "zara1")
#: Target closed-loop ADE of the noisy-oracle reference arms, metres (as in the ablation).
NOISY_ORACLE_ADE_M: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
#: The arms the benchmarked predictor is tested against (paired, Holm-corrected over scenes and references).
REFERENCES: tuple[str, ...] = ("cv", "oracle")


@dataclass(frozen=True)
class PlannerCell:
    """One evaluation of the sampling planner: a forecast arm on a held-out scene."""

    scene: str
    """The split whose held-out scene is replayed."""
    arm: str
    """Arm label: the predictor's name, ``cv``, ``oracle`` or ``noisy_oracle_<ade>``."""
    predictor: str
    """The environment's ``predictor`` (a forecast source, plug-in name or import path)."""
    env_overrides: Mapping[str, Any] = field(default_factory=dict)
    """Environment settings of the arm (``noisy_oracle_ade_m`` for the sweep)."""

    @property
    def path(self) -> str:
        """Folder of the cell relative to the bench's ``planner/`` folder."""
        return f"{self.scene}/{self.arm.replace(':', '_').replace('/', '_')}"


def planner_cells(
    predictor: str, scenes: Sequence[str] = DEFAULT_SCENES, noisy: Sequence[float] = NOISY_ORACLE_ADE_M
) -> list[PlannerCell]:
    """The bench's planner cells: per scene the predictor, cv, oracle and the noisy-oracle sweep."""
    cells = []
    for scene in scenes:
        cells.append(PlannerCell(scene, predictor, predictor))
        cells += [PlannerCell(scene, ref, ref) for ref in REFERENCES if ref != predictor]
        cells += [
            PlannerCell(scene, f"noisy_oracle_{ade:g}", "noisy_oracle", {"noisy_oracle_ade_m": float(ade)})
            for ade in noisy
        ]
    return cells


#: Runs one cell: ``(cell, folder, episodes, seed) -> None``, writing ``episodes.csv`` and ``summary.json``.
CellRunner = Callable[[PlannerCell, Path, int, int], None]


def local_runner(n_envs: int = 4, progress: bool = False) -> CellRunner:
    """Evaluate a cell in this process (:func:`agents.evaluate.evaluate` with the sampling planner)."""

    def run(cell: PlannerCell, folder: Path, episodes: int, seed: int) -> None:
        from agents.evaluate import evaluate

        evaluate(
            "planner",
            cell.predictor,
            cell.scene,
            episodes,
            seed=seed,
            out_dir=folder,
            env_overrides=dict(cell.env_overrides),
            n_envs=n_envs,
            progress=progress,
        )

    return run


def cell_key(cell: PlannerCell, episodes: int, seed: int, fingerprint: str) -> dict[str, Any]:
    """What a finished cell must match to be reused."""
    return {"cell": asdict(cell), "episodes": episodes, "seed": seed, "fingerprint": fingerprint}


def _done(folder: Path, key: Mapping[str, Any]) -> bool:
    try:
        held = json.loads((folder / "cell.json").read_text())
    except (OSError, ValueError):
        return False
    return held == json.loads(json.dumps(key)) and (folder / "episodes.csv").is_file()


def run_cells(
    cells: Sequence[PlannerCell],
    root: str | Path,
    episodes: int,
    seed: int,
    fingerprint_of: Callable[[PlannerCell], str],
    runner: CellRunner,
    log: Callable[[str], None] = lambda _m: None,
) -> dict[str, int]:
    """Run every cell not yet done (resumable); returns ``{"ran", "skipped"}``.

    Args:
        fingerprint_of: what determines a cell's forecasts (the predictor's fingerprint for its scene; a constant
            for cv/oracle/noisy oracle).
        runner: evaluates one cell (:func:`local_runner`).
    """
    ran = skipped = 0
    for cell in cells:
        folder = Path(root) / cell.path
        key = cell_key(cell, episodes, seed, fingerprint_of(cell))
        if _done(folder, key):
            skipped += 1
            continue
        log(f"  planner {cell.scene} / {cell.arm}: {episodes} episodes")
        runner(cell, folder, episodes, seed)
        atomic_write_json(folder / "cell.json", key)
        ran += 1
    log(f"  planner cells: ran {ran}, reused {skipped}")
    return {"ran": ran, "skipped": skipped}


def read_cell(root: str | Path, cell: PlannerCell) -> dict[str, Any]:
    """A finished cell: ``summary`` (summary.json) and ``success`` ``(episodes,)`` bool in episode order."""
    folder = Path(root) / cell.path
    summary = json.loads((folder / "summary.json").read_text())
    with open(folder / "episodes.csv", newline="") as fh:
        rows = sorted(csv.DictReader(fh), key=lambda r: int(r["episode"]))
    success = np.array([r["outcome"] == "success" for r in rows], dtype=bool)
    return {"summary": summary, "success": success}


def planner_results(predictor: str, cells: Sequence[PlannerCell], root: str | Path) -> dict[str, Any]:
    """Per scene and arm: success rate with its Wilson interval and closed-loop forecast ADE; and the paired
    tests (exact McNemar on success, same episodes) of the predictor against each reference, Holm-corrected over
    all of them.
    """
    arms: dict[str, dict[str, Any]] = {}
    success: dict[tuple[str, str], np.ndarray] = {}
    for cell in cells:
        data = read_cell(root, cell)
        s = data["success"]
        success[(cell.scene, cell.arm)] = s
        lo, hi = wilson_interval(int(s.sum()), len(s))
        arms.setdefault(cell.scene, {})[cell.arm] = {
            "episodes": len(s),
            "success_rate": float(s.mean()) if len(s) else float("nan"),
            "success_ci": [lo, hi],
            "forecast_ade_m": data["summary"].get("forecast_ade_m_mean"),
            "noisy_oracle_ade_m": cell.env_overrides.get("noisy_oracle_ade_m"),
        }
    tests = []
    for scene in dict.fromkeys(c.scene for c in cells):
        for ref in REFERENCES:
            if ref == predictor or (scene, ref) not in success:
                continue
            t = mcnemar_exact(success[(scene, predictor)], success[(scene, ref)])
            tests.append({"scene": scene, "a": predictor, "b": ref, **t})
    if tests:
        for t, adj in zip(tests, holm([t["p_value"] for t in tests]), strict=True):
            t["p_holm"] = adj
    return {"arms": arms, "tests": tests}
