"""A tiny real ablation grid on both backends: real evaluations (and training, once per backend), tiny budgets.

The crowd is the synthetic one, so these run without the ETH/UCY data.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import agents.ablation as ab


def _config(tmp_path: Path, policies: dict[str, Any], arms: list[str]) -> ab.AblationConfig:
    raw: dict[str, Any] = {
        "name": "e2e",
        "runs_dir": str(tmp_path / "runs"),
        "out_dir": str(tmp_path / "results"),
        "splits": ["zara1"],
        "arms": arms,
        "seeds": [0],
        "policies": policies,
        "evaluation": {"episodes": 3, "seed": 0},
        "env": {"crowd": "synthetic"},
        "comparisons": [[arms[-1], arms[0]]],
    }
    return ab.config_from_mapping(raw)


def _check_done(cfg: ab.AblationConfig, names: list[str]) -> None:
    states = {st.cell.name: st.state for st in ab.plan(cfg)}
    assert states == dict.fromkeys(names, "done")
    for name in names:
        if name.startswith("eval/"):
            rows = ab.read_episodes(ab.cell_dir(cfg, name) / "episodes.csv")
            assert len(rows) == cfg.episodes
    summary = json.loads((cfg.out_path() / "summary.json").read_text())
    assert summary["complete"] is True


PLANNER_CELLS = ["eval/zara1/planner/none", "eval/zara1/planner/cv"]


def test_local_pool_runs_planner_cells_and_skips_them_after(tmp_path: Path) -> None:
    cfg = _config(tmp_path, {"planner": {"kind": "planner"}}, ["none", "cv"])
    result = ab.run_grid(cfg, backend="local", workers=2, out=lambda s: None)
    assert sorted(result["ran"]) == sorted(PLANNER_CELLS) and not result["failed"]
    _check_done(cfg, PLANNER_CELLS)
    assert ab.run_grid(cfg, backend="local", workers=2, summarize_after=False, out=lambda s: None)["ran"] == []


@pytest.mark.slow
def test_ray_backend_gathers_cells_through_return_values(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    cfg = _config(tmp_path, {"planner": {"kind": "planner"}}, ["none", "cv"])
    result = ab.run_grid(cfg, backend="ray", workers=1, out=lambda s: None)
    assert sorted(result["ran"]) == sorted(PLANNER_CELLS) and not result["failed"]
    _check_done(cfg, PLANNER_CELLS)
    meta = json.loads((ab.cell_dir(cfg, PLANNER_CELLS[0]) / ab.CELL_JSON).read_text())
    assert meta["status"] == "done" and meta["episodes_per_s"] > 0
