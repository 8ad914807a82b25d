"""Training configs: the RL Zoo layout, overrides, validation, the algorithm's arguments."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import yaml

from agents.runs import PROJECT_KEY
from agents.training.config import (
    ENV_ID_OF,
    ZOO_KEYS,
    LinearSchedule,
    algorithm_kwargs,
    load_train_config,
    policy_class,
)
from crowdnav_mesrnn.config import ConfigError, load_yaml

REPO = Path(__file__).resolve().parents[3]
PPO_YAML = REPO / "configs" / "agent" / "ppo.yaml"
SAC_YAML = REPO / "configs" / "agent" / "sac.yaml"
SMOKE_YAML = REPO / "configs" / "agent" / "ppo_smoke.yaml"


@pytest.mark.parametrize("path", [PPO_YAML, SAC_YAML, SMOKE_YAML])
def test_config_files_are_rl_zoo_entries_per_env_id(path: Path) -> None:
    """What RL Zoo does with an entry: drop its own keys and pass the rest to the algorithm's constructor."""
    from stable_baselines3 import PPO, SAC

    raw = yaml.safe_load(path.read_text())
    algo = raw[PROJECT_KEY]["algo"]
    params = inspect.signature({"ppo": PPO, "sac": SAC}[algo].__init__).parameters
    for env_id in set(ENV_ID_OF.values()):
        entry = dict(raw[env_id])
        assert entry == raw["CrowdNav-MESRNN-v0"]  # every arm the same hyperparameters
        assert isinstance(entry["policy_kwargs"], dict)  # plain data (RL Zoo would eval a string)
        assert policy_class(entry["policy"]).__module__ == "agents.extractors"
        for key in ZOO_KEYS:
            entry.pop(key, None)
        assert set(entry) <= set(params), set(entry) - set(params)


def test_overrides_go_to_the_entry_or_the_project_section() -> None:
    cfg = load_train_config(
        PPO_YAML,
        None,
        {
            "predictor": "cv",
            "split": "univ",
            "seed": 3,
            "learning_rate": "lin_1e-3",
            "env.time_penalty": -0.01,
            "eval.episodes": 7,
            "policy_kwargs.net_arch": [32],
            "pretrain.episodes": 5,
        },
    )
    assert (cfg.algo, cfg.env_id, cfg.predictor, cfg.split, cfg.seed) == ("ppo", "CrowdNav-CV-v0", "cv", "univ", 3)
    assert cfg.env["time_penalty"] == -0.01 and cfg.env["observe_time_left"] is True
    assert cfg.eval.episodes == 7 and cfg.policy_kwargs["net_arch"] == [32]
    shipped = load_yaml(PPO_YAML)["CrowdNav-MESRNN-v0"]["policy_kwargs"]["features_extractor_kwargs"]
    assert cfg.policy_kwargs["features_extractor_kwargs"] == shipped  # siblings of the overridden key kept
    assert cfg.pretrain is not None and cfg.pretrain.episodes == 5 and cfg.pretrain.teacher == "planner"
    kwargs = algorithm_kwargs(cfg)
    assert isinstance(kwargs["learning_rate"], LinearSchedule) and kwargs["learning_rate"](0.5) == 5e-4
    assert cfg.env_kwargs("val") == {
        **cfg.env,
        "predictor": "cv",
        "split": "univ",
        "part": "train",
        "episode_time": "val",
    }
    # a second load is unaffected (the YAML aliases are copied, not shared)
    assert (
        load_train_config(PPO_YAML).policy_kwargs["net_arch"]
        == load_yaml(PPO_YAML)["CrowdNav-MESRNN-v0"]["policy_kwargs"]["net_arch"]
    )
    assert load_train_config(PPO_YAML, None, {"predictor": "srnn"}).env_id == "CrowdNav-MESRNN-v0"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"learning_rat": 1e-3}, "learning_rat"),
        ({"env.colision_penalty": -1}, "colision_penalty"),
        ({"env.predictor": "cv"}, "set by the run"),
        ({"env.time_penalty": "x"}, "time_penalty"),
        ({"eval.episode": 3}, "episode"),
        ({"pretrain.teacher": "ppo"}, "teacher"),
        ({"policy_kwargs": "dict(net_arch=[64])"}, "eval"),
        ({"n_timesteps": -5}, "n_timesteps"),
        ({"predictor": "lstm"}, "predictor"),
        ({"vec_env": "ray"}, "vec_env"),
        ({"frame_stack": 4}, "frame_stack"),
    ],
)
def test_bad_configs_name_the_key(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_train_config(PPO_YAML, None, overrides)


def test_missing_entry_lists_the_entries(tmp_path: Path) -> None:
    path = tmp_path / "x.yaml"
    path.write_text("CrowdNav-CV-v0: {n_timesteps: 10, policy: MultiInputPolicy}\ncrowdnav_mesrnn: {algo: ppo}\n")
    with pytest.raises(ConfigError, match="CrowdNav-CV-v0"):
        load_train_config(path)
    assert load_train_config(path, None, {"predictor": "cv"}).policy == "MultiInputPolicy"


SCORING_YAML = REPO / "configs" / "agent" / "ppo_scoring.yaml"
FAST_YAML = REPO / "configs" / "agent" / "ppo_scoring_fast.yaml"


def test_the_fast_candidate_differs_from_the_recipe_only_where_it_declares() -> None:
    """configs/agent/ppo_scoring_fast.yaml: the shipped recipe but for the learning settings its comments name
    (n_envs, n_steps, batch_size; the rollout size kept) and the vectorised environment; it loads for every arm and
    steps the batched environment."""
    from agents.training.config import vec_env_kind

    fast, recipe = load_yaml(FAST_YAML), load_yaml(SCORING_YAML)
    entry, shipped = fast["CrowdNav-MESRNN-v0"], recipe["CrowdNav-MESRNN-v0"]
    assert all(fast[env_id] == entry for env_id in set(ENV_ID_OF.values()))  # every arm the same hyperparameters
    assert {k for k in entry.keys() | shipped.keys() if entry.get(k) != shipped.get(k)} == {
        "n_envs",
        "n_steps",
        "batch_size",
    }
    assert entry["n_envs"] * entry["n_steps"] == shipped["n_envs"] * shipped["n_steps"]
    project, shipped_project = fast[PROJECT_KEY], recipe[PROJECT_KEY]
    assert {k for k in project.keys() | shipped_project.keys() if project.get(k) != shipped_project.get(k)} == {
        "vec_env"
    }
    for arm in ("none", "cv", "mesrnn", "oracle"):
        cfg = load_train_config(FAST_YAML, None, {"predictor": arm})
        assert vec_env_kind(cfg) == ("vector", None)
        assert algorithm_kwargs(cfg)["batch_size"] == 512


@pytest.mark.parametrize(
    ("anchor", "misspelt"),
    [("  batch_size: 512\n", "  n_epoch: 3\n"), ("  vec_env: vector\n", "  vec_envs: dummy\n")],
)
def test_the_fast_candidate_refuses_unknown_keys(tmp_path: Path, anchor: str, misspelt: str) -> None:
    text = FAST_YAML.read_text()
    assert anchor in text
    path = tmp_path / "fast.yaml"
    path.write_text(text.replace(anchor, anchor + misspelt, 1))
    with pytest.raises(ConfigError, match=misspelt.split(":")[0].strip()):
        load_train_config(path)
