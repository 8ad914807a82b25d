"""The SB3 adapter of the batched environment gives what SB3's DummyVecEnv over the training environments gives, and
is what agents.train steps by default (``vec_env: auto``) where the batched environment can run the settings."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv

from agents.actions import action_set
from agents.batched_vec_env import BatchedVecEnv
from agents.runs import PROJECT_KEY
from agents.training.config import _algo_class, algorithm_kwargs, load_train_config, policy_class, vec_env_kind
from agents.training.run import make_env, make_vec_env
from crowdnav_mesrnn.config import ConfigError
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


def test_reset_with_options_per_environment_keeps_each_ones_reset_info() -> None:
    env_kwargs = {"predictor": "cv", "crowd": "synthetic", "synthetic_duration_s": 120.0}
    dummy = DummyVecEnv([lambda: make_env(env_kwargs, None) for _ in range(3)])
    batched = BatchedVecEnv(3, env_kwargs)
    for venv in (dummy, batched):
        venv.seed(5)
        venv.set_options([{"time_limit_s": 2.0}, {"time_limit_s": 3.2}, None])
    obs_d, obs_b = dummy.reset(), batched.reset()
    _same(obs_d, obs_b, "obs")
    _same(dummy.reset_infos, batched.reset_infos, "reset_infos")
    assert [info["time_limit_s"] for info in batched.reset_infos][:2] == [2.0, 3.2]
    dummy.close()
    batched.close()


def test_the_shared_environment_is_not_reset_or_set_per_index_behind_the_adapter() -> None:
    venv = BatchedVecEnv(3, {"predictor": "none", "crowd": "empty"})
    venv.reset()
    for name in ("reset", "step", "close"):
        with pytest.raises(NotImplementedError, match=f"env_method\\('{name}'\\).*all 3 environments"):
            venv.env_method(name, indices=[1])
    with pytest.raises(NotImplementedError, match="set_attr\\('foo'\\) with indices=\\[0\\]"):
        venv.set_attr("foo", 5, indices=[0])
    venv.set_attr("foo", 5)
    assert venv.get_attr("foo", indices=[0, 2]) == [5, 5]
    assert venv.get_attr("observation_space") == [venv.observation_space] * 3
    assert venv.get_attr("action_space", indices=1) == [venv.action_space]
    venv.close()


def test_ppo_learns_on_the_adapter() -> None:
    venv = BatchedVecEnv(2, {"predictor": "cv", "crowd": "synthetic", "synthetic_duration_s": 60.0})
    model = PPO("MultiInputPolicy", venv, n_steps=16, batch_size=16, policy_kwargs={"net_arch": [16]}, device="cpu")
    model.learn(64)
    assert model.num_timesteps >= 64
    assert venv.get_attr("num_envs") == [2, 2] and venv.env_is_wrapped(object) == [False, False]
    assert len(venv.env_method("precompute_forecasts")) == 2
    venv.close()


# ---------------------------------------------------------------------------------------------- agents.train


class _Transitions(BaseCallback):
    """Every collected transition: observations, actions, rewards and dones as the algorithm stores them."""

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[dict[str, Any]] = []

    def _on_step(self) -> bool:
        loc = self.locals
        self.steps.append(
            {
                "obs": {k: np.array(v) for k, v in loc["new_obs"].items()},
                "actions": np.array(loc.get("clipped_actions", loc.get("actions"))),
                "rewards": np.array(loc["rewards"]),
                "dones": np.array(loc["dones"]),
                "ends": [
                    (info["episode"]["r"], info["episode"]["l"], info["is_success"], info["TimeLimit.truncated"])
                    for info in loc["infos"]
                    if "episode" in info
                ],
                "terminal": [info["terminal_observation"] for info in loc["infos"] if "terminal_observation" in info],
            }
        )
        return True


def _short_run(algo: str, overrides: dict[str, Any], vec_env: str, config_of: Any) -> tuple[list, dict[str, Any]]:
    """A short training run as agents.train builds it (config, VecEnv, algorithm): its transitions and final weights."""
    cfg = load_train_config(config_of(algo), None, {**overrides, "vec_env": vec_env})
    venv = make_vec_env(cfg)
    model = _algo_class(algo)(
        policy_class(cfg.policy), venv, seed=cfg.seed, verbose=0, device="cpu", **algorithm_kwargs(cfg)
    )
    record = _Transitions()
    model.learn(cfg.n_timesteps, callback=record)
    weights = {k: v.detach().clone() for k, v in model.policy.state_dict().items()}
    venv.close()
    return record.steps, weights


@pytest.mark.parametrize(
    ("algo", "predictor", "extra"),
    [
        ("ppo", "cv", {"n_envs": 3, "n_steps": 32, "n_timesteps": 192}),  # discrete goal-relative actions
        ("sac", "none", {"n_envs": 2, "n_timesteps": 96, "learning_starts": 48}),  # continuous actions
    ],
)
def test_a_short_training_run_on_the_adapter_has_the_transitions_of_dummy_vec_env(
    algo: str, predictor: str, extra: dict[str, Any], tiny: Any, config_of: Any
) -> None:
    overrides = {**tiny(algo, predictor), **extra, "pretrain": None, "env.synthetic_duration_s": 60.0}
    dummy, w_dummy = _short_run(algo, overrides, "dummy", config_of)
    vector, w_vector = _short_run(algo, overrides, "vector", config_of)
    assert len(vector) == len(dummy) == extra["n_timesteps"] // extra["n_envs"]
    for t, (a, b) in enumerate(zip(dummy, vector, strict=True)):
        for key in a["obs"]:
            np.testing.assert_array_equal(b["obs"][key], a["obs"][key], err_msg=f"step {t} obs {key}")
        for name in ("actions", "rewards", "dones"):
            np.testing.assert_array_equal(b[name], a[name], err_msg=f"step {t} {name}")
        assert b["ends"] == a["ends"], f"step {t}"
        for x, y in zip(a["terminal"], b["terminal"], strict=True):
            for key in x:
                np.testing.assert_array_equal(y[key], x[key], err_msg=f"step {t} terminal {key}")
    assert sum(len(s["ends"]) for s in dummy) >= 1  # an episode ended (and was reset) inside the run
    for key, value in w_dummy.items():  # the same updates from the same transitions
        assert np.array_equal(w_vector[key].numpy(), value.numpy()), key


def test_auto_is_the_batched_env_where_it_can_run_the_settings(tiny: Any, config_of: Any, tmp_path: Path) -> None:
    cfg = load_train_config(config_of("ppo"), None, {**tiny("ppo", "cv"), "vec_env": "auto"})
    assert vec_env_kind(cfg) == ("vector", None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning
        venv = make_vec_env(cfg)
    assert isinstance(venv, BatchedVecEnv)
    venv.close()
    # the default when a config does not set it
    doc = yaml.safe_load(config_of("ppo").read_text())
    del doc[PROJECT_KEY]["vec_env"]
    (tmp_path / "ppo.yaml").write_text(yaml.safe_dump(doc))
    assert load_train_config(tmp_path / "ppo.yaml", None, tiny("ppo", "cv")).vec_env == "auto"


@pytest.mark.parametrize("reaction", ["pause", "orca"])
def test_reacting_pedestrians_refuse_vector_and_make_auto_fall_back_with_a_warning(
    reaction: str, tiny: Any, config_of: Any
) -> None:
    over = {**tiny("ppo", "cv", n_envs=2), "env.reaction": reaction}
    with pytest.raises(ConfigError, match=f"vec_env 'vector'.*'reaction' = '{reaction}'.*'dummy'"):
        load_train_config(config_of("ppo"), None, {**over, "vec_env": "vector"})
    cfg = load_train_config(config_of("ppo"), None, {**over, "vec_env": "auto", "train_env.reaction": "none"})
    assert vec_env_kind(cfg) == ("vector", None)  # the training environments' own reaction decides
    cfg = load_train_config(config_of("ppo"), None, {**over, "vec_env": "auto"})
    kind, why = vec_env_kind(cfg)
    assert kind == "subproc" and f"'reaction' = '{reaction}'" in (why or "")
    cfg = load_train_config(config_of("ppo"), None, {**over, "vec_env": "auto", "n_envs": 1})
    with pytest.warns(UserWarning, match=f"vec_env 'auto' steps the training environments with 'dummy'.*{reaction}"):
        venv = make_vec_env(cfg)
    assert isinstance(venv, DummyVecEnv)
    venv.close()


def test_more_environments_than_the_batched_env_holds(tiny: Any, config_of: Any) -> None:
    with pytest.raises(ConfigError, match=r"n_envs = 300.*at most 256"):
        load_train_config(config_of("ppo"), None, {**tiny("ppo", "cv", n_envs=300), "vec_env": "vector"})
    cfg = load_train_config(config_of("ppo"), None, {**tiny("ppo", "cv", n_envs=300), "vec_env": "auto"})
    assert vec_env_kind(cfg)[0] == "subproc"


def _unbatch_reference(info: dict[str, Any], num: int) -> list[dict[str, Any]]:
    """Per-environment info dicts the plain way: environment by environment, key by key."""
    import math

    out: list[dict[str, Any]] = [{} for _ in range(num)]
    for key, value in info.items():
        if key.startswith("_") or f"_{key}" not in info:
            continue
        for i in range(num):
            if not info[f"_{key}"][i]:
                continue
            if isinstance(value, dict):
                out[i][key] = _unbatch_reference(value, num)[i]
                continue
            item = value[i] if value.dtype == object else value[i].tolist()
            out[i][key] = None if isinstance(item, float) and math.isnan(item) else item
    return out


def test_unbatched_infos_equal_the_plain_loop() -> None:
    """The adapter's info unbatching (one tolist per key, NaNs found at once) gives, value for value and type for type,
    what a loop over environments and keys gives: masks, NaN -> None in float arrays only, 2-D rows, object arrays,
    nested dicts."""
    from agents.batched_vec_env import _unbatch

    full, some = np.ones(4, dtype=bool), np.array([True, False, True, False])
    info = {
        "time_s": np.array([0.4, np.nan, 1.2, 2.0]),
        "_time_s": full,
        "min_gap_m": np.array([np.nan, 0.5, np.nan, 3.0], dtype=np.float32),
        "_min_gap_m": some,
        "collision": np.array([False, True, False, True]),
        "_collision": full,
        "count": np.arange(4),
        "_count": some,
        "position": np.array([[0.0, np.nan], [1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]),
        "_position": full,
        "fault": np.array(["robot", None, float("nan"), "pedestrian"], dtype=object),
        "_fault": full,
        "reward_components": {"progress": np.array([0.1, np.nan, 0.3, 0.4]), "_progress": full},
        "_reward_components": some,
        "unmasked": np.zeros(4),
    }
    got, want = _unbatch(info, 4), _unbatch_reference(info, 4)
    assert repr(got) == repr(want)  # every value (NaN included: repr 'nan') and every key in the same order
    for g, w in zip(got, want, strict=True):
        for key in w:
            assert type(g[key]) is type(w[key]), key
    assert got[1]["time_s"] is None and got[0]["min_gap_m"] is None and got[2]["fault"] is None
    assert got[0]["position"][1] != got[0]["position"][1]  # a NaN inside a row stays a float
