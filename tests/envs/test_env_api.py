"""The Gymnasium API: checkers, registration, seeding, spaces, bad input and configuration errors."""

from __future__ import annotations

import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml
from gymnasium.utils.env_checker import check_env, data_equivalence
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import crowdnav_mesrnn  # noqa: F401  (registers the ids)
from crowdnav_mesrnn._registration import ENV_IDS
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data import ENV_VAR, SPLIT_TEST_RECORDINGS, DataNotFoundError
from envs.config import CrowdNavConfig, default_config
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.factory import PredictorUnavailableError, load_learned

REPO = Path(__file__).resolve().parents[2]


def _checked_without_warnings(env: gym.Env) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped)
    messages = [str(w.message) for w in caught]
    assert not messages, messages


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_registered_ids_pass_gymnasium_and_sb3_checkers(env_id: str, data_dir: Path, fake_predictor: Callable) -> None:
    kwargs: dict[str, Any] = {"data_dir": str(data_dir)}
    if ENV_IDS[env_id] in ("mesrnn", "srnn", "vlstm"):
        # The pretrained weights may not exist yet: a stand-in with the same interface
        # (test_mesrnn_id_with_pretrained_weights runs the real one when they do).
        kwargs["predictor"] = fake_predictor("mesrnn-stand-in")
    env = gym.make(env_id, **kwargs)
    assert env.unwrapped.crowd_kind == "replay"
    _checked_without_warnings(env)
    env.close()


@pytest.mark.slow
def test_mesrnn_id_with_pretrained_weights(data_dir: Path) -> None:
    # The weights ship with the package: a missing file is a failure, not a skip.
    for split, recordings in SPLIT_TEST_RECORDINGS.items():
        load_learned("mesrnn", split, recordings[0])
    env = gym.make("CrowdNav-MESRNN-v0", data_dir=str(data_dir))
    assert env.unwrapped.predictor_name == "mesrnn"
    _checked_without_warnings(env)


@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
def test_synthetic_crowd_passes_checkers(kinematics: str) -> None:
    env = gym.make("CrowdNav-CV-v0", crowd="synthetic", kinematics=kinematics)
    _checked_without_warnings(env)


def test_make_in_a_fresh_interpreter() -> None:
    code = (
        "import gymnasium\n"
        "env = gymnasium.make('crowdnav_mesrnn:CrowdNav-NoPred-v0', crowd='synthetic')\n"
        "obs, info = env.reset(seed=0)\n"
        "import sys; print(sorted(obs), 'pymunk' in sys.modules, 'torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO, check=True
    )
    assert out.stdout.strip() == "['mask', 'pedestrians', 'robot'] True False"


def _random_episode(env: CrowdNavEnv, seed: int, max_steps: int = 60) -> list[tuple[Any, ...]]:
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    out: list[tuple[Any, ...]] = [(obs, info)]
    for _ in range(max_steps):
        step = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        out.append(step)
        if step[2] or step[3]:
            break
    return out


@pytest.mark.parametrize("predictor", ["cv", "noisy_oracle"])
def test_same_seed_gives_identical_episode(data_dir: Path, predictor: str) -> None:
    a = CrowdNavEnv(predictor=predictor, data_dir=str(data_dir))
    b = CrowdNavEnv(predictor=predictor, data_dir=str(data_dir))
    ep_a, ep_b = _random_episode(a, 7), _random_episode(b, 7)
    assert len(ep_a) == len(ep_b)
    assert data_equivalence(ep_a, ep_b, exact=True)
    # the same env reset with the same seed again: identical too; another seed: different
    assert data_equivalence(_random_episode(a, 7), ep_a, exact=True)
    assert not data_equivalence(_random_episode(a, 8)[0], ep_a[0])


def test_every_arm_gets_the_same_episodes(data_dir: Path) -> None:
    """The noisy oracle's noise must not consume the generator episodes are drawn from."""
    episodes: dict[str, list[tuple[Any, ...]]] = {}
    for predictor in ("none", "cv", "noisy_oracle"):
        env = CrowdNavEnv(predictor=predictor, data_dir=str(data_dir), split="univ", part="test")
        _, info = env.reset(seed=5)
        seq = []
        for _ in range(4):
            seq.append((info["recording"], info["t0_s"], info["start"], info["goal"]))
            for _ in range(5):
                *_, terminated, truncated, _ = env.step(np.zeros(2, dtype=np.float32))
                if terminated or truncated:
                    break
            _, info = env.reset()  # unseeded: continues the generator
        episodes[predictor] = seq
    assert episodes["noisy_oracle"] == episodes["none"] == episodes["cv"]


@pytest.mark.parametrize(
    ("predictor", "flatten", "reaction"),
    [("none", True, "none"), ("cv", False, "none"), ("oracle", True, "none"), ("cv", False, "orca")],
)
def test_the_true_future_a_teacher_reads_is_the_oracle_arms_forecasts(
    data_dir: Path, predictor: str, flatten: bool, reaction: str
) -> None:
    """Any arm's ``true_future_forecasts`` equals, step for step, the ``forecasts`` of an oracle-arm environment in the
    same episode under the same actions (rows, frame, clipping, layout); among reacting pedestrians too, where both
    are the recorded (counterfactual) future of the people perceived where they actually are."""
    kw = {"data_dir": str(data_dir), "split": "univ", "part": "test", "flatten_observation": flatten}
    kw["reaction"] = reaction
    env, oracle = CrowdNavEnv(predictor=predictor, **kw), CrowdNavEnv(predictor="oracle", **kw)
    rng = np.random.default_rng(3)
    compared = reacted = 0
    for seed in (11, 12):
        obs, _ = env.reset(seed=seed)
        want, _ = oracle.reset(seed=seed)
        for _ in range(40):
            got = env.true_future_forecasts()
            assert got.dtype == np.float32 and got.shape == want["forecasts"].shape
            np.testing.assert_array_equal(got, want["forecasts"])
            np.testing.assert_array_equal(obs["mask"], want["mask"])
            compared += int(want["mask"].sum())
            action = rng.uniform(-1, 1, 2).astype(np.float32)
            obs, _, terminated, truncated, _ = env.step(action)
            want, *_ = oracle.step(action)
            reacted += reaction != "none" and bool(env._reactive.crowd.reacting.any())
            if terminated or truncated:
                break
    assert compared > 0, "some pedestrian was perceived"
    assert (reacted > 0) == (reaction != "none"), "among reacting pedestrians someone reacted"


@pytest.mark.parametrize(
    "kwargs",
    [
        {"predictor": "none"},
        {"predictor": "cv", "kinematics": "unicycle"},
        {"predictor": "oracle", "flatten_observation": False},
        {"predictor": "noisy_oracle", "split": "univ", "part": "test"},
        {"predictor": "cv", "split": "eth", "part": "test", "terminate_on_collision": False},
    ],
)
def test_observation_inside_its_space_at_every_step(data_dir: Path, kwargs: dict[str, Any]) -> None:
    env = CrowdNavEnv(data_dir=str(data_dir), **kwargs)
    env.action_space.seed(0)
    obs, _ = env.reset(seed=0)
    assert obs in env.observation_space
    for _ in range(300):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert obs in env.observation_space, obs
        assert np.isfinite(reward)
        if terminated or truncated:
            obs, _ = env.reset()
            assert obs in env.observation_space


def test_observations_are_fresh_arrays(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="cv", data_dir=str(data_dir))
    first, _ = env.reset(seed=1)
    second, *_ = env.step(np.zeros(2, dtype=np.float32))
    for key in first:
        assert not np.shares_memory(first[key], second[key]), key


@pytest.mark.parametrize(
    ("action", "shown"),
    [
        (np.array([np.nan, 0.0]), "nan"),
        (np.array([0.0, np.inf]), "inf"),
        (np.zeros(3), "shape (3,)"),
        (np.zeros((1, 2)), "shape (1, 2)"),
        ([0.1], "[0.1]"),
        ("fast", "'fast'"),
    ],
)
def test_bad_actions_raise_value_error_showing_the_value(action: Any, shown: str) -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action") as info:
        env.step(action)
    assert shown in str(info.value)


def test_out_of_range_actions_are_clipped() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty")
    env.reset(seed=0, options={"start": (0.0, 0.0), "goal": (10.0, 0.0)})
    env.step(np.array([5.0, 0.0], dtype=np.float32))
    np.testing.assert_allclose(env.robot_position, [0.4, 0.0], atol=1e-12)


def test_step_before_reset_and_after_the_end_raise() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty", time_limit_factor=0.1)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2))
    env.reset(seed=0, options={"start": (0.0, 0.0), "goal": (8.0, 0.0)})
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(np.zeros(2))
        done = terminated or truncated
    assert truncated and info["episode_metrics"]["outcome"] == "timeout"
    with pytest.raises(RuntimeError, match="ended"):
        env.step(np.zeros(2))
    env.reset()
    env.step(np.zeros(2))


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"bogus_key": 1}, r"unknown env config key 'bogus_key' \(valid keys: .*dt_s.*split"),
        ({"split": "paris"}, r"unknown split 'paris'; valid: eth, hotel, univ, zara1, zara2"),
        ({"part": "val"}, r"unknown part 'val'; valid: train, test"),
        (
            {"predictor": "oracel"},
            r"unknown predictor 'oracel'; valid: none, cv, cv_gaussian, mesrnn, srnn, vlstm, oracle, noisy_oracle",
        ),
        ({"crowd": "real"}, r"unknown crowd 'real'; valid: auto, replay, synthetic, empty"),
        ({"kinematics": "diff"}, r"unknown kinematics 'diff'; valid: holonomic, unicycle"),
        (
            {"split": "zara1", "part": "test", "scenes": ("hotel",)},
            r"unknown scene 'hotel'.*valid: crowds_zara01, zara1",
        ),
        ({"dt_s": -0.4}, r"'dt_s' must be a number > 0, got -0.4"),
        ({"physics_dt_s": 0.4}, r"'physics_dt_s' = 0.4 is too long"),
        ({"terminate_on_collision": "no"}, r"must be true or false"),
    ],
)
def test_bad_configuration_lists_the_valid_values(kwargs: dict[str, Any], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        CrowdNavEnv(**{"crowd": "empty", "predictor": "none", **kwargs})


def test_scenes_select_recordings(data_dir: Path) -> None:
    env = CrowdNavEnv(
        predictor="none", data_dir=str(data_dir), split="zara1", part="train", scenes=("univ", "biwi_eth")
    )
    assert [r.name for r in env.recordings] == ["students001", "students003", "biwi_eth"]
    train = CrowdNavEnv(predictor="none", data_dir=str(data_dir), split="zara1", part="train")
    assert sorted(r.name for r in train.recordings) == sorted(
        ["biwi_eth", "biwi_hotel", "students001", "students003", "crowds_zara02"]
    )


def test_default_yaml_matches_the_code_and_loads(tmp_path: Path) -> None:
    path = REPO / "configs" / "env" / "default.yaml"
    assert yaml.safe_load(path.read_text()) == default_config()
    env = CrowdNavEnv(config=str(path), crowd="empty", predictor="none")
    assert env.config == CrowdNavConfig(crowd="empty", predictor="none")
    custom = tmp_path / "env.yaml"
    custom.write_text("num_pedestrians: 3\nhorizon_steps: 5\n")
    env = CrowdNavEnv(config=str(custom), crowd="empty", predictor="cv")
    assert env.observation_space["forecasts"].shape == (3 * 5 * 2,)
    # keywords override the config mapping
    assert CrowdNavEnv(config={"dt_s": 0.2}, dt_s=0.8, crowd="empty", predictor="none").config.dt_s == 0.8


def test_missing_data_is_explained(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(DataNotFoundError, match=ENV_VAR):
        CrowdNavEnv(predictor="none", crowd="replay")
    with pytest.raises(DataNotFoundError, match="typo"):
        CrowdNavEnv(predictor="none", data_dir=str(tmp_path / "typo"))
    with pytest.warns(UserWarning, match=f"synthetic social-force crowd.*{ENV_VAR}"):
        env = CrowdNavEnv(predictor="none")
    assert env.crowd_kind == "synthetic"
    env.reset(seed=0)


def test_missing_weights_give_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from crowdnav_mesrnn import predictors
    from envs.forecasting import factory

    def missing(name: str, split: str | None = None) -> Any:
        raise FileNotFoundError(f"no file {name}_{split}.pt")

    monkeypatch.setattr(predictors, "load", missing)
    monkeypatch.setattr(factory, "_LOADED", {})
    with pytest.raises(PredictorUnavailableError) as info:
        CrowdNavEnv(predictor="srnn", crowd="synthetic", split="hotel")
    msg = str(info.value)
    assert "'srnn' predictor for split 'hotel'" in msg and "no file srnn_hotel.pt" in msg and "'cv'" in msg
