"""``crowdnav-mesrnn bench``: forecast accuracy of any predictor against CV, the planner cells, the report, resuming."""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from agents.bench.metrics import protocol_batch_fn
from agents.bench.planner import bench_grid
from agents.bench.run import BenchConfig, run_bench
from agents.stats import VERDICTS
from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data.windows import split_windows
from crowdnav_mesrnn.evaluation.metrics import cv_predict_batch, window_errors
from crowdnav_mesrnn.evaluation.protocol import split_norm
from crowdnav_mesrnn.models import ConstantVelocity

PLUGIN = '''
import numpy as np

VERSION = "{version}"


class Still:
    """Everyone stays where last seen."""

    name = "still"
    obs_len = 8
    pred_len = 12

    def __init__(self, split=None):
        pass

    def cache_fingerprint(self):
        return VERSION

    def forecast(self, history, mask):
        t_last = np.where(mask, np.arange(mask.shape[0])[:, None], 0).max(axis=0)
        last = history[t_last, np.arange(history.shape[1])]
        return np.repeat(last[:, None, :], 12, axis=1).astype(np.float32)
'''


@pytest.fixture
def still_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "still_bench_plugin.py").write_text(textwrap.dedent(PLUGIN.format(version="1")))
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("still_bench_plugin", None)
    return "still_bench_plugin:Still"


def test_protocol_wrapper_scores_constant_velocity_like_the_batched_code(data_dir: Path) -> None:
    windows = split_windows("eth", "test", min_scored=2)
    norm = split_norm("eth")
    ours = window_errors(protocol_batch_fn(ConstantVelocity()), windows, norm)
    ref = window_errors(cv_predict_batch, windows, norm)
    assert np.allclose(ours["ade_m"], ref["ade_m"], atol=1e-4) and np.array_equal(
        ours["pedestrians"], ref["pedestrians"]
    )


def test_bench_grid_pairs_the_predictor_with_the_references(tmp_path: Path) -> None:
    from agents.ablation.cells import expand

    cfg = bench_grid("mesrnn", tmp_path, ("univ",), 10, 0, (0.5,))
    assert [c.name for c in expand(cfg)] == [
        f"eval/univ/planner/{a}" for a in ("mesrnn", "cv", "oracle", "noisy_oracle-0.5")
    ]
    assert cfg.comparisons == (("mesrnn", "cv"), ("mesrnn", "oracle"))
    assert [a.label for a in bench_grid("cv", tmp_path, ("univ",), 10, 0, ()).arms] == ["cv", "oracle"]


@pytest.mark.slow
def test_bench_writes_the_report_and_resumes(data_dir: Path, tmp_path: Path, still_plugin: str) -> None:
    cfg = BenchConfig(
        still_plugin, splits=("eth",), scenes=("zara1",), episodes=3, noisy_oracle_ade_m=(1.0,), resamples=200
    )
    out = tmp_path / "bench"
    report = run_bench(cfg, out, workers=1)
    assert len(report["planner"]["cells"]["ran"]) == 4
    assert {p.name for p in out.iterdir()} >= {"report.md", "report.json", "success_vs_ade.png", "windows", "cells"}
    eth = report["predictor_metrics"]["splits"]["eth"]
    assert eth["windows"] == 70 and eth["ade_m"] > eth["cv_ade_m"]  # standing still loses to CV on ETH
    assert eth["ade_m_diff_ci"][0] > 0
    arms = report["planner"]["arms"]["zara1"]
    assert arms["oracle"]["forecast_ade_m"] == pytest.approx(0.0, abs=1e-9)
    assert {(t["a"], t["b"]) for t in report["planner"]["tests"]} == {(still_plugin, "cv"), (still_plugin, "oracle")}
    for t in report["planner"]["tests"]:  # the interval agrees with the test; each cell has a plain verdict
        lo, hi = t["difference_exact_ci"]
        assert (lo > 0 or hi < 0) == (t["p_value"] < 0.05) and t["verdict"] in VERDICTS
    page = (out / "report.md").read_text()
    assert "| eth | 70 |" in page and "exact McNemar" in page and "success_vs_ade.png" in page
    assert "| verdict |" in page
    assert json.loads((out / "report.json").read_text())["predictor"] == still_plugin

    again = run_bench(cfg, out, workers=1)  # everything done: nothing runs again
    assert again["planner"]["cells"]["ran"] == []

    # a new version of the plug-in (its fingerprint) re-runs its own cell only
    Path(sys.modules["still_bench_plugin"].__file__).write_text(textwrap.dedent(PLUGIN.format(version="2")))
    sys.modules.pop("still_bench_plugin", None)
    third = run_bench(cfg, out, workers=1)
    assert third["planner"]["cells"]["ran"] == [f"eval/zara1/planner/{still_plugin}"]


def test_bench_cli_forecast_accuracy_only(data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cv"
    argv = ["bench", "cv", "--splits", "eth", "--no-planner", "--resamples", "200", "--out", str(out)]
    assert main(argv) == 0
    report = json.loads((out / "report.json").read_text())
    eth = report["predictor_metrics"]["splits"]["eth"]
    assert eth["ade_m_diff"] == pytest.approx(0.0, abs=1e-6) and "planner" not in report
    assert "not run" in (out / "report.md").read_text()
    # a subset run into the same folder would drop the eth row: refused, the report kept
    assert main(["bench", "cv", "--splits", "hotel", "--no-planner", "--resamples", "200", "--out", str(out)]) == 2
    assert "holds splits ['eth'] that this run would drop" in capsys.readouterr().err
    assert json.loads((out / "report.json").read_text())["predictor_metrics"]["splits"].keys() == {"eth"}


def test_bench_rejects_unknown_predictors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "nope", "--out", str(tmp_path / "x")]) == 2
    assert "unknown predictor 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_planner_table_gives_an_interval_that_agrees_with_its_test_and_a_verdict() -> None:
    """Issue 31: the page once printed "kalman − cv | −15.0 [−40.0, −5.0] | p 0.25". 3 of 20 episodes discordant,
    all against kalman: the exact conditional interval holds 0, and the verdict says no difference was shown."""
    from agents.bench.report import render_markdown
    from agents.stats import holm, mcnemar_exact, paired_verdict

    a = [0] * 3 + [1] * 10 + [0] * 7
    b = [1] * 13 + [0] * 7
    tests = [{"scene": "zara1", "a": "kalman", "b": "cv", **mcnemar_exact(a, b)}]
    tests.append({"scene": "zara1", "a": "kalman", "b": "oracle", **mcnemar_exact([1] * 20, [0] * 10 + [1] * 10)})
    for t, adj in zip(tests, holm([t["p_value"] for t in tests]), strict=True):
        t.update(p_holm=adj, verdict=paired_verdict(t["difference"], adj))
    arm = {"episodes": 20, "success_rate": 0.5, "success_ci": [0.3, 0.7], "forecast_ade_m": 0.3}
    report = {
        "predictor": "kalman",
        "command": "crowdnav-mesrnn bench kalman",
        "code_version": "test",
        "episodes": 20,
        "planner": {"arms": {"zara1": {"kalman": {**arm, "noisy_oracle_ade_m": None}}}, "tests": tests},
    }
    page = render_markdown(report)
    assert "| zara1 | kalman − cv | −15.0 [−15.0, +6.2] | 0.25 | 0.25 | no difference shown |" in page
    assert "| zara1 | kalman − oracle | +50.0 [+19.2, +50.0] | 0.00195 | 0.00391 | better than oracle |" in page
