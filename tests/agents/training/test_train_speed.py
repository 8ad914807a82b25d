"""benchmarks/train_speed.py: the ``--json`` object (the arms' steps/s and the split of a step measured inside one
training run), from a tiny real run on the synthetic crowd. Nothing here asserts on time."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[3]
SCORING_YAML = REPO / "configs" / "agent" / "ppo_scoring.yaml"
PHASES = {"env", "policy_forward", "update", "other"}
#: A few seconds: two environments, 16-step rollouts, one epoch, the synthetic crowd (no data needed).
TINY = {"env.crowd": "synthetic", "n_envs": 2, "n_steps": 16, "batch_size": 16, "n_epochs": 1}


def _script(monkeypatch: pytest.MonkeyPatch) -> Any:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))  # as `python benchmarks/train_speed.py` finds _timing
    spec = importlib.util.spec_from_file_location("train_speed", REPO / "benchmarks" / "train_speed.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_json_gives_each_arm_its_rate_and_split_per_step(monkeypatch: pytest.MonkeyPatch) -> None:
    bench = _script(monkeypatch)
    out = bench.run_json(SCORING_YAML, ["none", "cv"], ["vector", "dummy"], 32, "zara1", TINY, matmul_repeats=1)
    assert json.loads(json.dumps(out)) == out  # plain JSON
    assert set(out["arms"]) == {"none", "cv"} and set(out["split_us"]) == {"none", "cv"}
    assert (out["vec_env"], out["n_envs"]) == ("vector", 2)
    assert out["by_vec_env"]["vector"]["arms"] == out["arms"]
    assert out["by_vec_env"]["dummy"]["vec_env"] == "dummy"
    assert out["ratio_vs_none"]["none"] == 1.0
    assert out["cpu_count"] == os.cpu_count() and out["matmul_gflops"] > 0
    assert len(out["load_average"]["start"]) == len(out["load_average"]["end"]) == 3
    for kind in ("vector", "dummy"):
        figures = out["by_vec_env"][kind]
        for arm, rate in figures["arms"].items():
            split = figures["split_us"][arm]
            assert set(split) == PHASES and set(figures["cpu_split_us"][arm]) == PHASES
            assert all(split[p] > 0 for p in ("env", "policy_forward", "update"))
            # the phases account for the whole timed run: they add up to the time per step of the rate
            assert sum(split.values()) == pytest.approx(1e6 / rate, rel=2e-3)
