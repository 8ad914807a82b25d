"""Evaluation: the fixed episode list, aggregates and intervals on known inputs, files, policies of every kind."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from agents.evaluate import (
    EPISODE_COLUMNS,
    METRICS,
    OUTCOMES,
    episodes_csv,
    evaluate,
    evaluation_seeds,
    format_summary,
    load_policy,
    main,
    run_episodes,
    summarise,
)
from agents.planners import SamplingPlanner
from crowdnav_mesrnn.data import ENV_VAR
from envs.crowd_nav import CrowdNavEnv

SYNTHETIC = {"crowd": "synthetic"}


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval written out (an independent check of agents.stats through summarise)."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def hand_made_rows() -> list[dict]:
    outcomes = ["success"] * 7 + ["collision"] * 2 + ["timeout"]
    rows = []
    for i, outcome in enumerate(outcomes):
        rows.append(
            {
                "episode": i,
                "seed": 100 + i,
                "outcome": outcome,
                "navigation_time_s": 10.0 + i if outcome == "success" else 99.0,
                "path_ratio": 1.5,
                "min_gap_m": None if i == 9 else 0.1 * i,
                "forecast_ade_m": None,
                "steps": 20,
                "return": float(i),
            }
        )
    return rows


def test_summary_rates_have_wilson_intervals_and_counts() -> None:
    s = summarise(hand_made_rows())
    assert s["episodes"] == 10
    for name, k in (("success", 7), ("collision", 2), ("timeout", 1)):
        assert s[f"{name}_rate"] == pytest.approx(k / 10)
        assert s[f"{name}_count"] == k
        np.testing.assert_allclose(s[f"{name}_ci"], wilson(k, 10), rtol=1e-9)
    assert "successs" not in s and "timeouts" not in s
    json.dumps(s)  # JSON-ready


def test_the_table_separates_every_label_from_its_value() -> None:
    s = summarise(hand_made_rows())
    s.update(policy="straight", split="zara1", predictor="none", crowd={"kind": "synthetic", "data_dir": None})
    lines = format_summary(s).splitlines()[1:]
    assert len(lines) == len(OUTCOMES) + len(METRICS)
    matches = [re.match(r"^  (\S.*?\S)(\s{2,})(-|-?\d+\.\d{3})", line) for line in lines]
    assert all(matches), lines
    assert {m.start(3) for m in matches if m} == {matches[0].start(3)}, "values start in one column"
    assert ("navigation_time_s (successes)", "13.000") in {(m.group(1), m.group(3)) for m in matches if m}


def test_summary_means_use_the_episodes_each_metric_applies_to() -> None:
    s = summarise(hand_made_rows())
    # navigation time over the 7 successes only (10..16 s)
    assert s["navigation_time_s_mean"] == pytest.approx(13.0) and s["navigation_time_s_n"] == 7
    lo, hi = s["navigation_time_s_ci"]
    assert 10.0 <= lo < 13.0 < hi <= 16.0
    # a constant metric: a point interval
    assert s["path_ratio_mean"] == pytest.approx(1.5) and s["path_ratio_ci"] == [1.5, 1.5]
    # undefined values are left out; a metric defined nowhere has no mean
    assert s["min_gap_m_n"] == 9 and s["min_gap_m_mean"] == pytest.approx(0.4)
    assert s["forecast_ade_m_mean"] is None and s["forecast_ade_m_ci"] is None and s["forecast_ade_m_n"] == 0
    assert s["return_mean"] == pytest.approx(4.5)
    assert summarise([])["episodes"] == 0


def test_episodes_csv_has_the_interface_columns() -> None:
    text = episodes_csv(hand_made_rows())
    rows = list(csv.DictReader(text.splitlines()))
    assert list(rows[0]) == list(EPISODE_COLUMNS)
    assert rows[9]["min_gap_m"] == "" and rows[0]["outcome"] == "success"


def test_evaluation_seeds_are_fixed_nested_and_per_split() -> None:
    a = evaluation_seeds("zara1", 50)
    assert a == evaluation_seeds("zara1", 50) and evaluation_seeds("zara1", 20) == a[:20]
    assert a != evaluation_seeds("univ", 50) and a != evaluation_seeds("zara1", 50, seed=1)
    assert len(set(a)) == 50
    with pytest.raises(ValueError, match="split"):
        evaluation_seeds("zara3", 5)


def test_lockstep_episodes_do_not_depend_on_how_many_envs_run() -> None:
    seeds = evaluation_seeds("zara1", 6)
    results = []
    for n in (1, 3):
        envs = [CrowdNavEnv(predictor="cv", crowd="synthetic", part="test") for _ in range(n)]
        results.append(run_episodes(SamplingPlanner(envs[0].config), envs, seeds))
    assert results[0] == results[1]
    assert [r["seed"] for r in results[0]] == seeds


def test_evaluate_a_planner_writes_episodes_and_summary(tmp_path: Path) -> None:
    options = {"headings_deg": [0, 30, -30, 90, -90], "margin_m": 0.3}
    s = evaluate(
        "planner", "cv", "zara1", 6, out_dir=tmp_path, env_overrides=SYNTHETIC, n_envs=2, planner_kwargs=options
    )
    assert s["episodes"] == 6 and s["require_pedestrians"] is True and s["env"]["part"] == "test"
    assert s["planner"] == options
    for key in ("success_rate", "success_ci", "collision_rate", "collision_ci", "timeout_rate", "timeout_ci"):
        assert key in s
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["success_rate"] == s["success_rate"]
    rows = list(csv.DictReader((tmp_path / "episodes.csv").read_text().splitlines()))
    assert [int(r["seed"]) for r in rows] == evaluation_seeds("zara1", 6)
    assert all(r["forecast_ade_m"] != "" for r in rows if int(r["steps"]) > 0)


def test_evaluate_a_trained_run_with_its_own_env_settings(tiny_ppo_run: Path) -> None:
    s = evaluate(tiny_ppo_run, "none", "zara1", 3, env_overrides=SYNTHETIC, n_envs=1)
    assert s["episodes"] == 3 and s["model"].endswith("best_model.zip")
    assert s["env"]["observe_time_left"] is True  # from the run's config
    assert evaluate(tiny_ppo_run, "none", "zara1", 3, env_overrides=SYNTHETIC, which="final")["episodes"] == 3
    with pytest.raises(ValueError, match="trained on observations"):
        evaluate(tiny_ppo_run, "cv", "zara1", 2, env_overrides=SYNTHETIC)
    policy = load_policy(tiny_ppo_run / "final_model.zip")
    assert hasattr(policy, "predict")
    with pytest.raises(FileNotFoundError, match="planner"):
        load_policy("no/such/run")


def test_command_line_prints_one_json_object(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    args = ["straight", "--predictor", "none", "--episodes", "4", "--json", "--set", "crowd=synthetic"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["episodes"] == 4 and "success_ci" in out and "navigation_time_s_mean" in out
    assert (tmp_path / "episodes.csv").is_file() and out["out_dir"] == str(tmp_path)
    assert main(["ppo", "--episodes", "1"]) == 2


def test_without_out_the_episodes_go_to_a_new_folder_under_runs_eval(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    args = ["straight", "--predictor", "none", "--episodes", "2", "--set", "crowd=synthetic"]
    assert main(args) == 0
    assert main([*args, "--json"]) == 0
    folders = sorted((tmp_path / "runs" / "eval").iterdir())
    assert len(folders) == 2, "a second evaluation never overwrites the first"
    for folder in folders:
        assert folder.name.startswith("straight_none_zara1_s0_")
        with open(folder / "episodes.csv", newline="") as fh:
            assert len(list(csv.DictReader(fh))) == 2
        assert json.loads((folder / "summary.json").read_text())["episodes"] == 2
    out = capsys.readouterr().out
    text, json_line = out.strip().rsplit("\n", 1)
    named = {str(f.relative_to(tmp_path)) for f in folders}
    assert any(f"wrote {Path(n) / 'episodes.csv'}" in text for n in named)
    assert json.loads(json_line)["out_dir"] in named


def test_evaluating_a_scene_without_data_fails_naming_the_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    empty = tmp_path / "eth_ucy"
    empty.mkdir()
    monkeypatch.setenv(ENV_VAR, str(empty))
    monkeypatch.chdir(tmp_path)
    assert main(["planner", "--split", "zara1", "--episodes", "2"]) == 2
    err = capsys.readouterr().err
    assert str(empty) in err and "no ETH/UCY data found" in err
    assert not (tmp_path / "runs").exists(), "no result is written"


def test_every_summary_names_its_crowd_source(data_dir: Path) -> None:
    s = evaluate("straight", "none", "zara1", 1, env_overrides=SYNTHETIC, n_envs=1)
    assert s["crowd"] == {"kind": "synthetic", "data_dir": None}
    assert "synthetic crowd" in format_summary(s).splitlines()[0]
    s = evaluate("straight", "none", "zara1", 1, n_envs=1)
    assert s["crowd"] == {"kind": "replay", "data_dir": str(data_dir)}
    assert f"ETH/UCY replay from {data_dir}" in format_summary(s).splitlines()[0]


def test_summary_counts_popin_episodes_and_events() -> None:
    rows = hand_made_rows()
    for row, events in zip(rows, [0, 2, 0, 1, 0, 0, 0, 0, 0, 0], strict=True):
        row["popin_events"] = events
    s = summarise(rows)
    assert s["popin_episodes"] == 2 and s["popin_events"] == 3
    assert "popin_events" in EPISODE_COLUMNS
