"""The SB3 adapter of the batched environment gives what SB3's DummyVecEnv over the training environments gives."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv

from agents.batched_vec_env import BatchedVecEnv
from agents.train import action_set, make_env
from envs.config import config_from


def _same(a: Any, b: Any, where: str) -> None:
    if isinstance(a, dict):
        keys = set(a) - {"t"} if where.endswith("episode") else set(a)
        assert keys <= set(b) and (set(b) - keys) <= {"t"}, f"{where}: {sorted(set(a) ^ set(b))}"
        for key in keys:
            _same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(b, a, err_msg=where)
    else:
        assert type(a) is type(b) or {type(a), type(b)} <= {int, float}, f"{where}: {a!r} vs {b!r}"
        assert a == b, f"{where}: {a!r} != {b!r}"


@pytest.mark.parametrize(("predictor", "kind"), [("cv", "discrete"), ("none", "continuous")])
def test_transitions_equal_dummy_vec_env_over_single_envs(predictor: str, kind: str) -> None:
    env_kwargs = {"predictor": predictor, "crowd": "synthetic", "synthetic_duration_s": 120.0}
    action = {"kind": kind}
    dummy = DummyVecEnv([lambda: make_env(env_kwargs, action) for _ in range(3)])
    batched = BatchedVecEnv(3, env_kwargs, action_set(action, config_from(env_kwargs, {})))
    assert batched.action_space == dummy.action_space and batched.observation_space == dummy.observation_space
    for venv in (dummy, batched):
        venv.seed(11)
    obs_d, obs_b = dummy.reset(), batched.reset()
    rng = np.random.default_rng(0)
    ended = 0
    for t in range(120):
        _same(obs_d, obs_b, f"step {t} obs")
        _same(dummy.reset_infos, batched.reset_infos, f"step {t} reset_infos") if t == 0 else None
        if kind == "discrete":
            actions = rng.integers(0, dummy.action_space.n, size=3)
        else:
            actions = rng.uniform(-1, 1, size=(3, 2)).astype(np.float32)
        obs_d, rew_d, done_d, info_d = dummy.step(actions)
        obs_b, rew_b, done_b, info_b = batched.step(actions)
        assert rew_b.dtype == rew_d.dtype
        np.testing.assert_array_equal(rew_b, rew_d)
        np.testing.assert_array_equal(done_b, done_d)
        for i, (a, b) in enumerate(zip(info_d, info_b, strict=True)):
            _same(a, b, f"step {t} info[{i}]")
        ended += int(done_d.sum())
    assert ended >= 3  # same-step resets were compared
    dummy.close()
    batched.close()


def test_ppo_learns_on_the_adapter() -> None:
    venv = BatchedVecEnv(2, {"predictor": "cv", "crowd": "synthetic", "synthetic_duration_s": 60.0})
    model = PPO("MultiInputPolicy", venv, n_steps=16, batch_size=16, policy_kwargs={"net_arch": [16]}, device="cpu")
    model.learn(64)
    assert model.num_timesteps >= 64
    assert venv.get_attr("num_envs") == [2, 2] and venv.env_is_wrapped(object) == [False, False]
    assert len(venv.env_method("precompute_forecasts")) == 2
    venv.close()
