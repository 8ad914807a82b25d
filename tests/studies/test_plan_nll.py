"""A plan that selects on validation NLL (configs/predictor/gaussian.yaml): candidates, seeds to ship and the
runs' commands read the likelihood, not the ADE."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.studies.plan import candidate_runs, load_plan, run_dir, selected_candidate, summary
from crowdnav_mesrnn.training.trainer import load_configs

GAUSSIAN = Path(__file__).resolve().parents[2] / "configs" / "predictor" / "gaussian.yaml"


def fake_done(out: Path, ade: float, nll: float) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "done.json").write_text(json.dumps({"best_val_ade_m": ade, "best_val_nll_m": nll, "epochs": 8}))


def test_the_declared_plan_selects_on_nll(tmp_path: Path) -> None:
    text = GAUSSIAN.read_text().replace("out_dir: runs/predictor/gaussian", f"out_dir: {tmp_path}")
    (tmp_path / "plan.yaml").write_text(text)
    plan = load_plan(tmp_path / "plan.yaml")
    assert plan.select_on == "nll" and [c.name for c in plan.candidates] == ["residual", "residual_rotation"]
    runs = candidate_runs(plan)
    assert len(runs) == 30 and all("--set select_on=nll" in r.command() for r in runs)
    mcfg, tcfg = load_configs(runs[0].model, runs[0].candidate.config_path(runs[0].model), runs[0].overrides)
    assert mcfg.head == "gaussian" and mcfg.scale_detach and tcfg.mean_loss == "mse" and tcfg.select_on == "nll"
    # lower ADE but higher NLL loses
    fake_done(run_dir(plan, "mesrnn", "univ", "residual", 0), ade=0.40, nll=1.2)
    fake_done(run_dir(plan, "mesrnn", "univ", "residual_rotation", 0), ade=0.45, nll=0.9)
    cand, vals = selected_candidate(plan, "mesrnn", "univ")
    assert cand is not None and cand.name == "residual_rotation" and vals == {"residual": 1.2, "residual_rotation": 0.9}
    fake_done(run_dir(plan, "mesrnn", "univ", "residual_rotation", 1), ade=0.39, nll=1.0)
    fake_done(run_dir(plan, "mesrnn", "univ", "residual_rotation", 2), ade=0.46, nll=0.8)
    row = summary(plan)["mesrnn/univ"]
    assert row["shipped_seed"] == 2 and row["candidates_val_nll_m"] == vals


def test_select_on_is_checked(tmp_path: Path) -> None:
    (tmp_path / "p.yaml").write_text("select_on: fde\ncandidates:\n  a:\n    config: configs/predictor/{model}.yaml\n")
    with pytest.raises(ConfigError, match="'select_on' is 'fde'; valid: ade, nll"):
        load_plan(tmp_path / "p.yaml")
