"""``crowdnav-mesrnn demo`` with every kind of policy, and the ``agent`` subcommands."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image

import agents.cli
import agents.runs
from crowdnav_mesrnn.cli import main


@pytest.fixture
def exported(tiny_ppo_run: Path, tmp_path: Path) -> Path:
    dest = tmp_path / "pretrained" / "ppo_none.policy.yaml"
    assert main(["agent", "export", str(tiny_ppo_run), str(dest)]) == 0
    assert dest.is_file() and dest.with_name("ppo_none.pt").is_file()
    return dest


def test_demo_with_the_planner_on_the_synthetic_crowd(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gif_path = tmp_path / "planner.gif"
    args = ["demo", "--policy", "planner", "--synthetic", "--predictor", "cv", "--seed", "2", "--json"]
    assert main([*args, "--out", str(gif_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("demo: policy planner") and "(synthetic)" in lines[0]
    record = json.loads("\n".join(lines[1 : lines.index("}") + 1]))
    assert record["policy"] == "planner" and record["predictor"] == "cv" and record["forecast_ade_m"] is not None
    with Image.open(gif_path) as gif:
        assert gif.n_frames == record["steps"] + 1


def test_demo_with_a_trained_policy_uses_its_forecast_arm(exported: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--policy", str(exported), "--synthetic", "--no-gif", "--json"]) == 0
    record = json.loads(capsys.readouterr().out.split("\n", 1)[1].rsplit("\ndone in", 1)[0])
    assert record["predictor"] == "none" and record["policy"] == str(exported) and "outcome" in record
    # a policy trained without forecasts cannot read an observation with them
    assert main(["demo", "--policy", str(exported), "--synthetic", "--no-gif", "--predictor", "cv"]) == 2
    assert "trained on observations" in capsys.readouterr().err


def test_demo_defaults_to_the_shipped_policy_else_the_planner(
    exported: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(agents.cli, "SHIPPED_POLICY", exported.parent / "missing.policy.yaml")
    assert main(["demo", "--synthetic", "--no-gif", "--predictor", "cv"]) == 0
    captured = capsys.readouterr()
    assert "no shipped PPO policy" in captured.err and "policy planner" in captured.out
    monkeypatch.setattr(agents.cli, "SHIPPED_POLICY", exported)
    assert main(["demo", "--synthetic", "--no-gif"]) == 0
    assert f"policy {exported}" in capsys.readouterr().out
    assert main(["demo", "--synthetic", "--no-gif", "--split", "univ", "--predictor", "cv"]) == 0
    assert "the sampling planner crosses it instead" in capsys.readouterr().err


def test_agent_evaluate_subcommand(exported: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["agent", "evaluate", str(exported), "--predictor", "none", "--episodes", "2", "--json"]
    assert main([*args, "--set", "crowd=synthetic"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 2


def test_export_copies_the_policy_file_training_wrote(tiny_ppo_run: Path, exported: Path) -> None:
    """A run folder of ``agent train`` holds the policy file: export copies its weights, naming them after DEST."""
    from agents.runs import model_path

    source = model_path(tiny_ppo_run)
    assert source.name == "best_model.policy.yaml"
    assert exported.with_name("ppo_none.pt").read_bytes() == source.with_name("best_model.pt").read_bytes()
    assert "file: ppo_none.pt" in exported.read_text() and "best_model.pt" not in exported.read_text()
    with pytest.raises(ValueError, match=r"NAME\.policy\.yaml"):
        agents.runs.export_policy(tiny_ppo_run, exported.with_name("x.zip"))


def test_the_shipped_policy_crosses_the_held_out_zara1_scene(
    data_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The README's quick start: the shipped PPO policy with MESRNN forecasts on the real held-out scene."""
    if not agents.cli.SHIPPED_POLICY.is_file():
        pytest.fail(f"the shipped policy {agents.cli.SHIPPED_POLICY} is missing from the package")
    assert main(["demo", "--no-gif", "--json"]) == 0
    out = capsys.readouterr().out
    assert "policy" in out.splitlines()[0] and "ppo_mesrnn_zara1.policy.yaml" in out.splitlines()[0]
    assert '"outcome"' in out


@pytest.mark.parametrize("policy", ["search", "privileged"])
def test_demo_with_the_search_planner_and_the_privileged_ceiling(
    policy: str, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["demo", "--policy", policy, "--synthetic", "--predictor", "cv", "--no-gif", "--json"]
    assert main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    record = json.loads("\n".join(lines[1 : lines.index("}") + 1]))
    assert record["policy"] == policy and record["outcome"] in ("success", "collision", "timeout")
