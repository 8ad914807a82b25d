"""Evaluation end to end: files, policies of every kind, the command line, the crowd each summary names."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from agents.evaluation.cli import main
from agents.evaluation.run import evaluate
from agents.evaluation.summary import format_summary
from agents.rollout import evaluation_seeds
from agents.runs import UntrustedPolicyError, load_policy
from crowdnav_mesrnn.data import ENV_VAR

SYNTHETIC = {"crowd": "synthetic"}


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
    assert s["episodes"] == 3 and s["model"].endswith("best_model.policy.yaml")
    assert s["env"]["observe_time_left"] is True  # from the run's config
    assert evaluate(tiny_ppo_run, "none", "zara1", 3, env_overrides=SYNTHETIC, which="final")["episodes"] == 3
    with pytest.raises(ValueError, match="trained on observations"):
        evaluate(tiny_ppo_run, "cv", "zara1", 2, env_overrides=SYNTHETIC)
    policy = load_policy(tiny_ppo_run / "final_model.policy.yaml")
    assert hasattr(policy, "predict")
    with pytest.raises(UntrustedPolicyError, match="--trust-pickle"):
        load_policy(tiny_ppo_run / "final_model.zip")
    assert hasattr(load_policy(tiny_ppo_run / "final_model.zip", trust_pickle=True), "predict")
    with pytest.raises(FileNotFoundError, match="planner"):
        load_policy("no/such/run")


def test_command_line_prints_one_json_object(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    args = ["straight", "--predictor", "none", "--episodes", "4", "--json", "--set", "crowd=synthetic"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["episodes"] == 4 and "success_ci" in out and "navigation_time_s_mean" in out
    assert (tmp_path / "episodes.csv").is_file() and out["out_dir"] == str(tmp_path)
    assert main(["ppo", "--episodes", "1"]) == 2


def test_episodes_from_val_replays_the_training_scenes_validation_period(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from agents.evaluation import evaluation_env_kwargs

    assert evaluation_env_kwargs("straight", "none", "zara1")["part"] == "test"
    kwargs = evaluation_env_kwargs("straight", "none", "zara1", episodes_from="val")
    assert (kwargs["part"], kwargs["episode_time"]) == ("train", "val")
    with pytest.raises(ValueError, match=r"episodes_from must be one of test, val, got 'train'"):
        evaluation_env_kwargs("straight", "none", "zara1", episodes_from="train")
    args = ["straight", "--predictor", "none", "--episodes", "2", "--json", "--set", "crowd=synthetic"]
    assert main([*args, "--episodes-from", "val", "--out", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["env"]["part"], out["env"]["episode_time"]) == ("train", "val")


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
