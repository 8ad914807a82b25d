"""Short real PPO/SAC runs per forecast arm: the run folder, resuming, the warm start, the command line."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path
from typing import Any

import pytest
import yaml

from agents.policy_file import read_policy_file
from agents.runs import PROJECT_KEY
from agents.training.config import load_train_config
from agents.training.run import resolved_yaml, steps_trained, train
from crowdnav_mesrnn.config import ConfigError
from envs.crowd_nav import ENV_REVISION
from envs.reaction import MODEL_REVISIONS

ARMS = ("none", "cv", "mesrnn", "oracle")
REPO = Path(__file__).resolve().parents[3]
PPO_YAML = REPO / "configs" / "agent" / "ppo.yaml"
SAC_YAML = REPO / "configs" / "agent" / "sac.yaml"
SMOKE_YAML = REPO / "configs" / "agent" / "ppo_smoke.yaml"
RUN_FILES = (
    "config.yaml",
    "command.txt",
    "version.txt",
    "progress.csv",
    "evaluations.csv",
    "best_model.zip",
    "final_model.zip",
    "best_model.policy.yaml",
    "best_model.pt",
    "final_model.policy.yaml",
    "final_model.pt",
    "DONE",
)


def _check_run_folder(run: Path, steps: int, predictor: str) -> None:
    for name in RUN_FILES:
        assert (run / name).is_file(), name
    for which in ("best", "final"):  # the policy files load (nothing unpickled) as the zips they sit beside
        doc = read_policy_file(run / f"{which}_model.policy.yaml")
        assert doc.settings["run"]["predictor"] == predictor
    assert json.loads((run / "DONE").read_text())["steps"] == steps
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved[PROJECT_KEY]["run"]["predictor"] == predictor
    assert saved[PROJECT_KEY]["run"]["env_resolved"]["episode_time"] == "train"
    assert saved[PROJECT_KEY]["run"]["env_rules"] == {"env_revision": ENV_REVISION}
    if predictor == "mesrnn":
        weights = saved[PROJECT_KEY]["run"]["predictor_weights_sha256"]
        assert weights and all(len(v) == 64 for v in weights.values())
    with open(run / "progress.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    logged = [float(r["time/total_timesteps"]) for r in rows if r.get("time/total_timesteps")]
    assert logged == sorted(logged) and logged[-1] <= steps
    latest = json.loads((run / "checkpoints" / "latest.json").read_text())
    assert latest["steps"] == steps


def test_the_run_records_the_rules_its_environments_run_under() -> None:
    """config.yaml's run section names the environment's revision and, under a reaction model, the model, its
    parameters and its revision: a run trained under other rules is told apart without its grid."""
    cfg = load_train_config(SMOKE_YAML, overrides={"predictor": "cv", "split": "zara1", "env.crowd": "synthetic"})
    assert resolved_yaml(cfg)[PROJECT_KEY]["run"]["env_rules"] == {"env_revision": ENV_REVISION}
    cfg = load_train_config(
        SMOKE_YAML,
        overrides={"predictor": "cv", "split": "zara1", "env.crowd": "synthetic", "env.reaction": "social_force"},
    )
    rules = resolved_yaml(cfg)[PROJECT_KEY]["run"]["env_rules"]
    assert rules["reaction"] == "social_force" and rules["reaction_revision"] == MODEL_REVISIONS["social_force"] >= 2
    assert rules["env_revision"] == ENV_REVISION and rules["reaction_params"]


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo", "sac"])
@pytest.mark.parametrize("predictor", ARMS)
def test_short_run_writes_a_complete_folder_and_resumes(tmp_path: Path, algo: str, predictor: str, tiny: Any) -> None:
    path = PPO_YAML if algo == "ppo" else SAC_YAML
    run = tmp_path / "run"
    cfg = load_train_config(path, None, tiny(algo, predictor, steps=128))
    assert train(cfg, run, progress=False, command="pytest") == run
    _check_run_folder(run, 128, predictor)
    warm = [0] if cfg.pretrain is not None else []  # the warm-started policy is validated before any RL step
    with open(run / "evaluations.csv", newline="") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [*warm, 64, 128]

    more = load_train_config(path, None, tiny(algo, predictor, steps=192))
    train(more, run, resume=True, progress=False, command="pytest --resume")
    _check_run_folder(run, 192, predictor)
    assert "resumed from step_0000000128" in (run / "command.txt").read_text()
    with open(run / "evaluations.csv", newline="") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [*warm, 64, 128, 192]


def test_a_finished_or_foreign_folder_is_not_overwritten(tiny_ppo_run: Path, tmp_path: Path, tiny: Any) -> None:
    cfg = load_train_config(PPO_YAML, None, tiny("ppo", "none"))
    with pytest.raises(ConfigError, match="finished"):
        train(cfg, tiny_ppo_run, progress=False)
    assert train(cfg, tiny_ppo_run, resume=True, progress=False) == tiny_ppo_run  # nothing left to do
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        train(cfg, tmp_path / "other", progress=False)
    other = load_train_config(PPO_YAML, None, tiny("ppo", "none", steps=256, learning_rate=1e-3))
    with pytest.raises(ConfigError, match="learning_rate"):
        train(other, tiny_ppo_run, resume=True, progress=False)


def test_command_line_trains_and_resumes(tmp_path: Path, tiny: Any) -> None:
    from agents.training.cli import main

    run = tmp_path / "cli"
    sets = [f"--set={k}={json.dumps(v)}" for k, v in tiny("ppo", "cv", steps=64).items() if k != "predictor"]
    args = ["--config", str(PPO_YAML), "--predictor", "cv", "--seed", "1", "--out", str(run), "--no-progress"]
    assert main([*args, *sets]) == 0
    assert (run / "DONE").is_file()
    assert "--predictor cv" in (run / "command.txt").read_text()
    assert main(["--out", str(run), "--resume", "--timesteps", "128", "--no-progress"]) == 0
    assert json.loads((run / "DONE").read_text())["steps"] == 128
    assert main(["--config", str(PPO_YAML), "--set", "learning_rat=1"]) == 2


def test_warm_start_runs_before_rl_and_is_validated_at_step_zero(tmp_path: Path, tiny: Any) -> None:
    extra = {"pretrain.episodes": 3, "pretrain.epochs": 1, "pretrain.n_envs": 2, "pretrain.dagger_rounds": 0}
    cfg = load_train_config(PPO_YAML, None, tiny("ppo", "cv", steps=64, **extra))
    run = train(cfg, tmp_path / "bc", progress=False)
    stats = json.loads((run / "pretrain.json").read_text())
    assert stats["episodes"] == 3 and stats["transitions"] > 0 and stats["teacher"] == "planner"
    with open(run / "evaluations.csv", newline="") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [0, 64]


@pytest.mark.slow
def test_subprocess_workers_with_observation_normalisation_resume_and_evaluate(tmp_path: Path, tiny: Any) -> None:
    from agents.evaluation.run import evaluate

    extra = {"n_envs": 2, "vec_env": "subproc", "normalize": True, "n_steps": 32}
    run = tmp_path / "subproc"
    train(load_train_config(PPO_YAML, None, tiny("ppo", "cv", steps=128, **extra)), run, progress=False)
    for name in ("final_model_vecnormalize.pkl", "best_model_vecnormalize.pkl"):
        assert (run / name).is_file()
    assert (run / "checkpoints" / "step_0000000128" / "model_vecnormalize.pkl").is_file()
    train(load_train_config(PPO_YAML, None, tiny("ppo", "cv", steps=192, **extra)), run, resume=True, progress=False)
    assert json.loads((run / "DONE").read_text())["steps"] == 192
    assert evaluate(run, "cv", "zara1", 2, env_overrides={"crowd": "synthetic"}, n_envs=1)["episodes"] == 2


def test_discrete_goal_relative_actions_train_warm_start_and_evaluate(tmp_path: Path, tiny: Any) -> None:
    from agents.actions import DiscretePolicy
    from agents.evaluation.run import evaluate
    from agents.runs import load_policy

    extra = {"action.kind": "discrete", "pretrain.episodes": 3, "pretrain.epochs": 1}
    cfg = load_train_config(PPO_YAML, None, tiny("ppo", "cv", steps=64, **extra))
    assert cfg.action_set().n == 57
    run = train(cfg, tmp_path / "discrete", progress=False)
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved[PROJECT_KEY]["action"] == {"kind": "discrete"}
    policy = load_policy(run, cfg.env_kwargs("val"))
    assert isinstance(policy, DiscretePolicy)
    summary = evaluate(run, "cv", "zara1", 2, env_overrides={"crowd": "synthetic"}, n_envs=2)
    assert summary["episodes"] == 2
    with pytest.raises(ConfigError, match="ppo"):
        load_train_config(SAC_YAML, None, {"action.kind": "discrete"})
    with pytest.raises(ConfigError, match="kind"):
        load_train_config(PPO_YAML, None, {"action.kind": "polar"})
    with pytest.raises(ConfigError, match="headings"):
        load_train_config(PPO_YAML, None, {"action.kind": "discrete", "action.headings": [0]})


def test_the_run_folder_names_its_crowd_source(tiny_ppo_run: Path) -> None:
    run = yaml.safe_load((tiny_ppo_run / "config.yaml").read_text())["crowdnav_mesrnn"]["run"]
    assert run["crowd"] == {"kind": "synthetic", "data_dir": None}


def test_training_on_scenes_without_data_fails_before_the_run_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, tiny: Any
) -> None:
    from crowdnav_mesrnn.data import ENV_VAR, DataNotFoundError

    empty = tmp_path / "eth_ucy"
    empty.mkdir()
    monkeypatch.setenv(ENV_VAR, str(empty))
    cfg = load_train_config(PPO_YAML, None, tiny("ppo", "none", **{"env.crowd": "auto"}))
    with pytest.raises(DataNotFoundError, match=str(empty)):
        train(cfg, tmp_path / "run", progress=False, command="pytest")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("algo", "extra", "asked", "trained"),
    [
        ("ppo", {"n_steps": 256, "n_envs": 8}, 256, 2048),
        ("ppo", {"n_steps": 256, "n_envs": 8}, 100_000, 100_352),
        ("ppo", {"n_steps": 64, "n_envs": 1}, 128, 128),
        ("sac", {"n_envs": 2}, 101, 102),
        ("sac", {"n_envs": 2, "train_freq": 4}, 100, 104),
    ],
)
def test_steps_trained_round_up_to_whole_rollouts(algo: str, extra: dict, asked: int, trained: int, tiny: Any) -> None:
    path = PPO_YAML if algo == "ppo" else SAC_YAML
    cfg = load_train_config(path, None, tiny(algo, "none", steps=asked, **extra))
    assert steps_trained(cfg) == trained
    assert steps_trained(cfg, start_step=trained) == trained


def test_a_budget_that_is_not_whole_rollouts_is_named_with_what_is_trained(tmp_path: Path, tiny: Any) -> None:
    over = tiny("ppo", "none", steps=40, **{"pretrain": None, "eval.episodes": 0, "checkpoint_freq_steps": 0})
    cfg = load_train_config(PPO_YAML, None, over)
    with pytest.warns(UserWarning, match=r"n_timesteps 40 trains 64 steps.*n_steps 64 x n_envs 1 = 64"):
        run = train(cfg, tmp_path / "run", progress=False, command="pytest")
    assert json.loads((run / "DONE").read_text())["steps"] == 64


def test_without_tensorboard_the_run_says_once_that_it_writes_no_tb_logs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import importlib.util
    import warnings

    from agents.training import logger as train_module

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "tensorboard" else real(name, *a))
    monkeypatch.setattr(train_module, "_TB_NOTICE_SHOWN", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for k in range(3):
            train_module.make_logger(tmp_path / f"r{k}", None)
    notes = [str(w.message) for w in caught if "TensorBoard" in str(w.message)]
    assert len(notes) == 1 and "pip install 'crowdnav-mesrnn[tb]'" in notes[0]
    assert not (tmp_path / "r0" / "tb").exists()


def test_the_smoke_preset_is_the_recipe_shrunk_and_trains(tmp_path: Path) -> None:
    smoke = load_train_config(SMOKE_YAML, None, {"predictor": "cv"})
    recipe = load_train_config(PPO_YAML, None, {"predictor": "cv"})
    assert smoke.action == recipe.action and smoke.policy == recipe.policy and smoke.env == recipe.env
    assert smoke.pretrain is not None and smoke.pretrain.dagger_rounds >= 1
    assert smoke.n_timesteps % rollout_size(smoke) == 0, "no warning: the budget is whole rollouts"
    # a few of its steps, end to end (the synthetic crowd: no data needed; the preset's warm start and validation)
    cfg = load_train_config(SMOKE_YAML, None, {"predictor": "cv", "n_timesteps": 256, "env.crowd": "synthetic"})
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        run = train(cfg, tmp_path / "smoke", progress=False, command="pytest")
    done = json.loads((run / "DONE").read_text())
    assert done["steps"] == 256 and done["best_validation"] is not None
    assert (run / "pretrain.json").is_file() and (run / "best_model.zip").is_file()


def rollout_size(cfg: Any) -> int:
    return int(cfg.hyperparams["n_steps"]) * cfg.n_envs
