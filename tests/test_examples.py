"""The examples run (tiny budgets): the plug-in package through the bench, the train-and-evaluate script."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_the_plugin_example_is_an_installable_package() -> None:
    import tomllib

    meta = tomllib.loads((ROOT / "examples" / "kalman_predictor" / "pyproject.toml").read_text())
    assert meta["project"]["entry-points"][predictors.ENTRY_POINT_GROUP] == {
        "kalman": "kalman_predictor:KalmanPredictor"
    }


@pytest.mark.slow
def test_the_installed_plugin_is_benchmarked(data_dir: Path, tmp_path: Path) -> None:
    predictors.refresh()
    if "kalman" not in predictors.registered():
        if os.environ.get("CI"):
            pytest.fail("CI installs examples/kalman_predictor; its entry point 'kalman' is missing")
        pytest.skip("examples/kalman_predictor is not installed (pip install ./examples/kalman_predictor)")
    out = tmp_path / "bench"
    argv = ["bench", "kalman", "--splits", "eth", "--scenes", "zara1", "--episodes", "3", "--resamples", "200"]
    assert main([*argv, "--workers", "1", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["spec"]["distribution"] == "crowdnav-kalman-predictor"
    assert report["planner"]["arms"]["zara1"]["kalman"]["episodes"] == 3
    assert (out / "report.md").is_file() and (out / "success_vs_ade.png").is_file()


@pytest.mark.slow
def test_train_and_evaluate_example_runs(data_dir: Path, tmp_path: Path) -> None:
    (tmp_path / "configs").symlink_to(ROOT / "configs", target_is_directory=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "train_and_evaluate.py"),
            "--tiny",
            "--predictor",
            "cv",
            "--out",
            "out",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--- planner" in done.stdout and "success_rate" in done.stdout
    assert (tmp_path / "out" / "policy" / "DONE").is_file()
    assert (tmp_path / "out" / "policy" / "episodes.csv").is_file()
