"""The batched in-process vectorised environment gives what SB3's DummyVecEnv over the wrapped environments gives."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.training.config import load_train_config
from agents.training.run import make_vec_env

PPO_YAML = Path(__file__).resolve().parents[2] / "configs" / "agent" / "ppo.yaml"


@pytest.mark.parametrize(("predictor", "kind"), [("cv", "discrete"), ("none", "continuous")])
def test_batched_steps_like_dummy_over_the_wrappers(predictor: str, kind: str) -> None:
    over: dict[str, Any] = {"predictor": predictor, "n_envs": 3, "env.crowd": "synthetic", "action.kind": kind}
    if kind == "continuous":
        over["policy_kwargs.features_extractor_kwargs.frame"] = "world"
    dummy = make_vec_env(load_train_config(PPO_YAML, None, {**over, "vec_env": "dummy"}))
    batched = make_vec_env(load_train_config(PPO_YAML, None, {**over, "vec_env": "batched"}))
    assert batched.action_space == dummy.action_space and batched.observation_space == dummy.observation_space
    rng = np.random.default_rng(0)
    for venv in (dummy, batched):
        venv.seed(7)
    obs_d, obs_b = dummy.reset(), batched.reset()
    episodes = 0
    for _ in range(150):
        for key in obs_d:
            np.testing.assert_array_equal(obs_b[key], obs_d[key])
        if kind == "discrete":
            actions = rng.integers(0, dummy.action_space.n, size=3)
        else:
            actions = rng.uniform(-1, 1, size=(3, 2)).astype(np.float32)
        obs_d, rew_d, done_d, info_d = dummy.step(actions)
        obs_b, rew_b, done_b, info_b = batched.step(actions)
        np.testing.assert_array_equal(rew_b, rew_d)
        np.testing.assert_array_equal(done_b, done_d)
        for a, b in zip(info_d, info_b, strict=True):
            assert b["TimeLimit.truncated"] == a["TimeLimit.truncated"]
            assert ("episode" in b) == ("episode" in a) == ("terminal_observation" in a)
            if "episode" in a:
                episodes += 1
                assert (b["episode"]["r"], b["episode"]["l"]) == (a["episode"]["r"], a["episode"]["l"])
                assert b["is_success"] == a["is_success"]
                for key in a["terminal_observation"]:
                    np.testing.assert_array_equal(b["terminal_observation"][key], a["terminal_observation"][key])
    assert episodes >= 3  # resets inside the run were compared too
    dummy.close()
    batched.close()


def test_ppo_learns_on_the_batched_env(tiny: Any, config_of: Any, tmp_path: Path) -> None:
    from agents.training.run import train

    cfg = load_train_config(config_of("ppo"), None, tiny("ppo", "cv", vec_env="batched", n_envs=2))
    run = train(cfg, tmp_path / "batched", progress=False)
    assert (run / "DONE").is_file()
