"""The ablation summary with the metrics of issue 31: episodes that record them get the new columns, the exact
McNemar interval and a verdict; an archive written before them renders as it did (absent, not undefined)."""

from __future__ import annotations

import csv
import gzip
import json
from pathlib import Path
from typing import Any

import pytest

import agents.ablation as ab
from agents.stats import mcnemar_difference_ci

#                  episode: 0123456789ab
NONE_OUTCOMES: str = "SCCSCCTSCSCS"
CV_OUTCOMES: str = "SSSSSSSSSSSS"  # 7 discordant pairs, all for cv: p = 2 / 128


def _done_cell(cfg: ab.AblationConfig, name: str, rows: list[dict[str, Any]]) -> None:
    """A finished planner cell (planners need no training, their arms here no weights)."""
    cell = next(c for c in ab.expand(cfg) if c.name == name)
    folder = ab.cell_dir(cfg, cell)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "episodes.csv", "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    meta = {"spec": ab.cell_spec(cfg, cell), "weights": ab.weights_fingerprint(cell.arm.predictor), "wall_s": 1.0}
    (folder / ab.CELL_JSON).write_text(json.dumps(meta))
    (folder / ab.DONE).write_text("now\n")


def _config(tmp_path: Path, splits: list[str]) -> ab.AblationConfig:
    return ab.config_from_mapping(
        {
            "name": "tiny",
            "runs_dir": str(tmp_path / "runs"),
            "out_dir": str(tmp_path / "results"),
            "splits": splits,
            "arms": ["none", "cv"],
            "seeds": [0],
            "policies": {"planner": {"kind": "planner"}},
            "evaluation": {"episodes": 12, "seed": 0},
            "comparisons": [["cv", "none"]],
            "density_bins": [0.0, 12.0],
        }
    )


def _grid(tmp_path: Path, added: bool) -> ab.AblationConfig:
    cfg = _config(tmp_path, ["zara1"])
    code = {"S": "success", "C": "collision", "T": "timeout"}
    for arm, outcomes in (("none", NONE_OUTCOMES), ("cv", CV_OUTCOMES)):
        rows: list[dict[str, Any]] = [
            {"episode": i, "outcome": code[o], "navigation_time_s": 10.0, "path_ratio": 1.1, "crowd_density": float(i)}
            for i, o in enumerate(outcomes)
        ]
        if added:
            for r in rows:
                success = r["outcome"] == "success"
                r.update(path_ratio_required=1.25 if success else "", spl=0.8 if success else 0.0, min_ttc_s=2.0)
        _done_cell(cfg, f"eval/zara1/planner/{arm}", rows)
    return cfg


def test_episodes_with_the_added_metrics_get_columns_exact_intervals_and_verdicts(tmp_path: Path) -> None:
    cfg = _grid(tmp_path, added=True)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    cv = summary["policies"]["planner"]["arms"]["cv"]
    assert cv["spl_mean"] == pytest.approx(0.8) and cv["spl_n"] == 12
    assert cv["path_ratio_required_mean"] == pytest.approx(1.25) and cv["path_ratio_required_n"] == 12
    assert "mean_accel_mps2_mean" not in cv  # not recorded by these episodes: absent
    test = next(t for t in summary["tests"] if t["endpoint"] == "success")
    assert "difference_ci" not in test
    assert test["difference_exact_ci"] == pytest.approx(list(mcnemar_difference_ci(7, 0, 12)))
    assert test["verdict"] == "better" and test["p_holm"] <= 0.05
    with gzip.open(cfg.out_path() / "episodes" / "planner.csv.gz", "rt") as fh:
        header = fh.readline().strip().split(",")
    assert {"spl", "min_ttc_s", "path_ratio_required"} <= set(header) and "mean_accel_mps2" not in header
    md = (cfg.out_path() / "summary.md").read_text()
    assert "| SPL |" in md and "| min TTC s |" in md and "path ratio to required (successes)" in md
    assert "| verdict |" in md and "| better |" in md and "excludes 0 exactly when p < 0.05" in md


def test_an_archive_without_them_keeps_its_bootstrap_interval_and_columns(tmp_path: Path) -> None:
    cfg = _grid(tmp_path, added=False)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    assert "spl_mean" not in summary["policies"]["planner"]["arms"]["cv"]
    test = next(t for t in summary["tests"] if t["endpoint"] == "success")
    assert "difference_ci" in test and "difference_exact_ci" not in test and "verdict" not in test
    md = (cfg.out_path() / "summary.md").read_text()
    assert "| min gap m |" in md and "SPL" not in md and "verdict" not in md
    with gzip.open(cfg.out_path() / "episodes" / "planner.csv.gz", "rt") as fh:
        header = fh.readline().strip().split(",")
    assert "spl" not in header and "path_ratio" in header


def test_a_pooled_row_mixing_cells_with_and_without_them_shows_none_of_them(tmp_path: Path) -> None:
    """A cell reused from an older grid lacks the added metrics: the pooled mean over the other splits alone would pass
    for the whole arm's, so the pooled row leaves them undefined and says why; the per-split entries keep them."""
    cfg = _config(tmp_path, ["zara1", "eth"])
    for split in ("zara1", "eth"):
        for arm in ("none", "cv"):
            rows: list[dict[str, Any]] = [
                {"episode": i, "outcome": "success", "navigation_time_s": 10.0, "path_ratio": 1.1, "spl": "",
                 "min_ttc_s": "", "crowd_density": float(i)}
                for i in range(12)
            ]
            if split == "zara1" and arm == "cv":  # the only cell written after the metrics existed
                for r in rows:
                    r.update(spl=0.8, min_ttc_s=2.0)
            _done_cell(cfg, f"eval/{split}/planner/{arm}", rows)
    summary = ab.summarize(cfg, out=lambda s: None, plots=False)
    cv = summary["policies"]["planner"]["arms"]["cv"]
    assert cv["spl_mean"] is None and cv["spl_ci"] is None and cv["min_ttc_s_mean"] is None
    assert cv["spl_n"] == 12 and "spl" in cv["metrics_partly_recorded"]
    assert cv["navigation_time_s_mean"] == pytest.approx(10.0)  # recorded by every cell: pooled as before
    assert cv["by_split"]["zara1"]["spl_mean"] == pytest.approx(0.8)
    assert "metrics_partly_recorded" not in cv["by_split"]["zara1"]
    assert "metrics_partly_recorded" not in summary["policies"]["planner"]["arms"]["none"]  # no cell records them
    md = (cfg.out_path() / "summary.md").read_text()
    assert "a pooled mean would cover only the splits that record them" in md
