"""benchmarks/bf16_accuracy.py reuses a finished or interrupted run only when it was trained with the
configuration and seed being checked (a check of one configuration once reused another's bf16 runs)."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import pytest
import yaml

from crowdnav_mesrnn.training.trainer import load_configs

REPO = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("bf16_accuracy", REPO / "benchmarks" / "bf16_accuracy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _args(**changes) -> argparse.Namespace:
    base = {"model": "mesrnn", "split": "univ", "config": "configs/predictor/mesrnn.yaml", "set": None}
    return argparse.Namespace(**{**base, "seeds": [0, 1], "out": None, "fp32_from": None, **changes})


def _fake_run(folder: Path, config: str, overrides: dict) -> None:
    mcfg, tcfg = load_configs("mesrnn", REPO / config, overrides)
    folder.mkdir(parents=True)
    (folder / "run.yaml").write_text(yaml.safe_dump({"model": mcfg.to_dict(), "train": tcfg.__dict__}))


def test_each_configuration_has_its_own_folder_and_foreign_runs_are_refused(tmp_path: Path) -> None:
    bf16 = _script()
    paper = bf16.runs_for(_args())
    rotated = bf16.runs_for(_args(config="configs/predictor/mesrnn_residual.yaml", set=["augment_rotation=true"]))
    assert paper["bf16"][0].out == Path("runs/predictor/bf16/mesrnn/univ/mesrnn/bf16/seed0")
    assert rotated["bf16"][0].out == Path(
        "runs/predictor/bf16/mesrnn/univ/mesrnn_residual-augment_rotation=true/bf16/seed0"
    )

    out = tmp_path / "check"
    _fake_run(out / "bf16" / "seed0", "configs/predictor/mesrnn.yaml", {"precision": "bf16", "seed": 0})
    assert bf16.runs_for(_args(out=str(out)))["bf16"][0].out == out / "bf16" / "seed0"  # same recipe: reused
    with pytest.raises(SystemExit, match=r"run.yaml: model\.node_embed is 128, this check trains with 64"):
        bf16.runs_for(_args(out=str(out), config="configs/predictor/mesrnn_residual.yaml"))
    _fake_run(out / "fp32" / "seed1", "configs/predictor/mesrnn.yaml", {"precision": "fp32", "seed": 0})
    with pytest.raises(SystemExit, match=r"train\.seed is 0"):  # another seed's run in seed1's folder
        bf16.runs_for(_args(out=str(out)))
