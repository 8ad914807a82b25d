"""Fixtures of the agents tests: tiny training configs and one tiny trained PPO run shared by a session."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
PPO_YAML = REPO / "configs" / "agent" / "ppo.yaml"
SAC_YAML = REPO / "configs" / "agent" / "sac.yaml"


def tiny_overrides(algo: str, predictor: str, steps: int = 128, **extra: Any) -> dict[str, Any]:
    """Overrides making a training run take a few seconds: one environment, tiny networks, the synthetic
    crowd (no data needed), a 2-episode validation, a checkpoint every 64 steps and (PPO) a tiny warm start."""
    out: dict[str, Any] = {
        "predictor": predictor,
        "n_envs": 1,
        "n_timesteps": steps,
        "policy_kwargs.net_arch": [16],
        "policy_kwargs.features_extractor_kwargs.hidden_dim": 8,
        "eval.episodes": 2,
        "eval.n_envs": 2,
        "eval.freq_steps": 64,
        "checkpoint_freq_steps": 64,
        "env.crowd": "synthetic",
    }
    if algo == "ppo":
        out.update({"n_steps": 64, "batch_size": 32, "n_epochs": 1})
        # the shipped recipe's DAgger warm start, shrunk to two teacher and two student episodes
        out.update(
            {
                "pretrain.episodes": 2,
                "pretrain.epochs": 1,
                "pretrain.dagger_rounds": 1,
                "pretrain.dagger_episodes": 2,
                "pretrain.dagger_epochs": 1,
                "pretrain.n_envs": 2,
            }
        )
    else:
        out.update({"learning_starts": 32, "buffer_size": 500, "batch_size": 32})
    out.update(extra)
    return out


def agent_config(algo: str) -> Path:
    """The shipped training config of an algorithm."""
    return {"ppo": PPO_YAML, "sac": SAC_YAML}[algo]


@pytest.fixture
def tiny() -> Any:
    """:func:`tiny_overrides`."""
    return tiny_overrides


@pytest.fixture
def config_of() -> Any:
    """:func:`agent_config`."""
    return agent_config


@pytest.fixture(scope="session")
def tiny_ppo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished 128-step PPO run (``none`` arm, synthetic crowd)."""
    from agents.training import load_train_config, train

    cfg = load_train_config(PPO_YAML, None, tiny_overrides("ppo", "none"))
    return train(cfg, tmp_path_factory.mktemp("runs") / "ppo_none", progress=False, command="pytest")
