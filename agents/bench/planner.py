"""The planner half of ``crowdnav-mesrnn bench``: the sampling planner on held-out scenes with the benchmarked
predictor's forecasts, against constant velocity, the true future (oracle) and the noisy-oracle sweep on the same
seeded episodes, with paired tests.

These are the planner cells of the planning-aid ablation (``configs/ablation/planning_aid.yaml``) with the
predictor as one more arm, run by the ablation's grid machinery (:func:`agents.ablation.run_grid`: a local process
pool, or Ray with ``--backend ray``). Each cell is a folder under ``<out>/cells/`` with its spec and the
predictor's fingerprint (for a plug-in: its identity and weights, per split); a finished cell whose spec and
fingerprint match is reused, a stale one re-run, an interrupted one redone, so a bench resumes where it stopped.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agents.ablation.cells import Cell, cell_dir, expand
from agents.ablation.config import AblationConfig, config_from_mapping
from agents.ablation.episodes import read_episodes
from agents.stats import holm, mcnemar_exact, paired_verdict, wilson_interval
from crowdnav_mesrnn.config import ConfigError

#: Held-out scenes of the planning-aid ablation (its planner cells).
DEFAULT_SCENES: tuple[str, ...] = ("univ", "zara1")
#: Target closed-loop ADE of the noisy-oracle reference arms, metres (as in the ablation).
NOISY_ORACLE_ADE_M: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
#: The arms the benchmarked predictor is tested against (paired, Holm-corrected over scenes and references).
REFERENCES: tuple[str, ...] = ("cv", "oracle")
#: Family-wise error rate of the verdicts (Holm-adjusted p at most this: "better" or "worse").
ALPHA: float = 0.05


def bench_grid(
    predictor: str,
    root: str | Path,
    scenes: Sequence[str] = DEFAULT_SCENES,
    episodes: int = 500,
    seed: int = 0,
    noisy: Sequence[float] = NOISY_ORACLE_ADE_M,
    env: Mapping[str, Any] | None = None,
) -> AblationConfig:
    """The bench's grid: the sampling planner with arms ``predictor``, cv, oracle and the noisy-oracle sweep on
    ``scenes``; cells under ``root/cells``. Comparisons: the predictor against each reference."""
    arms = list(dict.fromkeys([predictor, *REFERENCES]))
    raw: dict[str, Any] = {
        "name": "bench",
        "description": f"crowdnav-mesrnn bench {predictor}: the planner cells of the planning-aid ablation",
        "splits": list(scenes),
        "arms": [*arms, *(["noisy_oracle"] if noisy else [])],
        "seeds": [0],
        "policies": {"planner": {"kind": "planner"}},
        "evaluation": {"episodes": int(episodes), "seed": int(seed)},
        "env": dict(env or {}),
        "comparisons": [[predictor, ref] for ref in REFERENCES if ref != predictor],
        "runs_dir": str(Path(root) / "cells"),
        "out_dir": str(Path(root) / "grid"),
    }
    if noisy:
        raw["noisy_oracle_ade_m"] = [float(v) for v in noisy]
    return config_from_mapping(raw, source="crowdnav-mesrnn bench")


def run_planner_cells(
    cfg: AblationConfig,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    log: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Run the cells not done yet through the grid machinery; ``{"ran", "failed", "skipped", "wall_s"}``.

    Raises:
        RuntimeError: a cell failed (its error, from its ``cell.json``).
    """
    from agents.ablation.backends import run_grid

    result = run_grid(cfg, backend=backend, workers=workers, address=address, summarize_after=False, out=log)
    if result["failed"]:
        name, error = next(iter(result["failed"].items()))
        raise RuntimeError(f"bench cell {name} failed: {error}")
    return result


def planner_results(cfg: AblationConfig, predictor: str) -> dict[str, Any]:
    """Per scene and arm: success rate with its Wilson interval and closed-loop forecast ADE; and the paired tests
    (exact McNemar on success, same episodes) of ``predictor`` against each reference, Holm-corrected over all, each
    with the exact conditional interval of the difference (``difference_exact_ci``: excludes 0 exactly when
    ``p_value < 0.05``, :func:`agents.stats.mcnemar_difference_ci`) and a plain ``verdict`` (``better``, ``worse``,
    ``no difference shown``: :func:`agents.stats.paired_verdict` on the Holm-adjusted p at :data:`ALPHA`)."""
    arms: dict[str, dict[str, Any]] = {}
    success: dict[tuple[str, str], np.ndarray] = {}
    for cell in expand(cfg):
        s, ade = _cell_outcomes(cfg, cell)
        success[(cell.split, cell.arm.label)] = s
        lo, hi = wilson_interval(int(s.sum()), len(s))
        arms.setdefault(cell.split, {})[cell.arm.label] = {
            "episodes": len(s),
            "success_rate": float(s.mean()) if len(s) else float("nan"),
            "success_ci": [lo, hi],
            "forecast_ade_m": ade,
            "noisy_oracle_ade_m": cell.arm.noisy_oracle_ade_m,
        }
    tests = []
    for scene in cfg.splits:
        for a, b in cfg.comparisons:
            t = mcnemar_exact(success[(scene, a)], success[(scene, b)])
            tests.append({"scene": scene, "a": a, "b": b, **t})
    for t, adj in zip(tests, holm([t["p_value"] for t in tests]) if tests else [], strict=True):
        t["p_holm"] = adj
        t["verdict"] = paired_verdict(t["difference"], adj, ALPHA)
    return {"arms": arms, "tests": tests, "alpha": ALPHA}


def _cell_outcomes(cfg: AblationConfig, cell: Cell) -> tuple[np.ndarray, float | None]:
    """``success (episodes,)`` bool in episode order and the mean closed-loop forecast ADE of a finished cell."""
    path = cell_dir(cfg, cell) / "episodes.csv"
    if not path.is_file():
        raise ConfigError(f"bench cell {cell.name} has no {path}; run the bench again to finish it")
    rows = sorted(read_episodes(path), key=lambda r: int(r["episode"]))
    success = np.array([r["outcome"] == "success" for r in rows], dtype=bool)
    ades = [float(r["forecast_ade_m"]) for r in rows if r.get("forecast_ade_m") not in (None, "", "nan")]
    return success, (float(np.mean(ades)) if ades else None)
