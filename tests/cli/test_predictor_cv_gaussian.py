"""``cv_gaussian`` on the command line: fitted by ``predictor fit-cv-gaussian``, accepted by ``evaluate`` (with the
sample scores) and ``calibrate`` like the heads, refused where it has no meaning."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from crowdnav_mesrnn.cli import build_parser, main
from crowdnav_mesrnn.models.cv_gaussian import load_cv_gaussian, load_params, params_path


def test_the_model_choices_and_their_help_come_from_the_registry() -> None:
    from crowdnav_mesrnn import predictors

    parser = build_parser("predictor")
    sub = next(a for a in parser._actions if a.dest == "command").choices["predictor"]
    actions = next(a for a in sub._actions if a.dest == "predictor_cmd").choices
    shipped = predictors.names(predictors.BASELINE, predictors.FITTED_BASELINE, predictors.PRETRAINED, plugins=False)
    for action in ("evaluate", "calibrate"):
        model = next(a for a in actions[action]._actions if a.dest == "model")
        assert tuple(model.choices) == shipped and all(name in model.help for name in shipped)
    assert "fit-cv-gaussian" in actions


def test_fit_cv_gaussian_writes_the_shipped_fit_and_never_overwrites_without_force(
    data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["predictor", "fit-cv-gaussian", "--split", "hotel", "--out-dir", str(tmp_path)]
    assert main([*argv, "--data-dir", str(data_dir)]) == 0
    _, fresh = load_params(params_path("hotel", tmp_path), "hotel")
    shipped = load_cv_gaussian("hotel").info
    assert {k: v for k, v in fresh.items() if k != "code_version"} == {
        k: v for k, v in shipped.items() if k != "code_version"
    }
    assert "b*h" in capsys.readouterr().out
    assert main(argv) != 0
    assert "exists: pass --force" in capsys.readouterr().err
    assert main([*argv, "--force", "--data-dir", str(data_dir)]) == 0


def test_evaluate_and_calibrate_take_cv_gaussian(data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "e.json"
    common = ["--model", "cv_gaussian", "--split", "hotel", "--resamples", "100", "--data-dir", str(data_dir)]
    assert main(["predictor", "evaluate", *common, "--samples", "4", "--sampling", "marginal", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    row = res["splits"]["hotel"]
    assert res["sampling"] == "marginal" and res["samples"] == 4 and res["checkpoints"]["hotel"]["form"] == "b*h"
    for key in ("nll_m", "energy_m", "min_ade_m", "scene_min_ade_m", "scene_min_fde_m", "coverage_90"):
        lo, hi = row[f"{key}_ci"]
        assert lo <= row[key] <= hi
    assert row["scene_min_ade_m"] >= row["min_ade_m"] and row["scene_min_fde_m"] >= row["min_fde_m"]
    cal = tmp_path / "c.json"
    assert main(["predictor", "calibrate", *common, "--levels", "0.9", "--out", str(cal)]) == 0
    calibrated = json.loads(cal.read_text())
    assert calibrated["head"] == "gaussian"
    # evaluate's coverage_90 is calibrate's pooled coverage of the same regions, to the digit
    assert calibrated["splits"]["hotel"]["coverage"]["0.9"] == pytest.approx(row["coverage_90"], abs=1e-12)
    capsys.readouterr()
    assert main(["predictor", "evaluate", *common, "--checkpoint", "x.pt"]) != 0
    assert "has none" in capsys.readouterr().err
    assert main(["predictor", "evaluate", "--model", "cv", "--split", "hotel", "--samples", "2"]) != 0
    assert "cv_gaussian" in capsys.readouterr().err
