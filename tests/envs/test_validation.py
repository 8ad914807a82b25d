"""Strict configuration and reset options: every class of mistake is refused with a message naming the key,
the value and what is allowed."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import crowdnav_mesrnn  # noqa: F401  (registers the ids)
from crowdnav_mesrnn.config import ConfigError
from envs.config import CrowdNavConfig
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording

BASE: dict[str, Any] = {"crowd": "empty", "predictor": "none"}
FIELDS = {f.name: f for f in dataclasses.fields(CrowdNavConfig)}
DEFAULTS = CrowdNavConfig()


def wrong_type(key: str) -> Any:
    """A value of the wrong type for ``key``."""
    default = getattr(DEFAULTS, key)
    if isinstance(default, bool):
        return "yes"
    if isinstance(default, tuple):
        return "ab"
    if isinstance(default, int):
        return 1.5
    if isinstance(default, float):
        return "x"
    if isinstance(default, str):
        return 3
    return 5  # folders: str or None


@pytest.mark.parametrize("key", sorted(FIELDS))
def test_every_key_refuses_a_wrong_type(key: str) -> None:
    value = wrong_type(key)
    with pytest.raises(ConfigError) as info:
        CrowdNavEnv(**{**BASE, key: value})
    message = str(info.value)
    assert key in message and repr(value) in message, message


REALS = [k for k, v in dataclasses.asdict(DEFAULTS).items() if isinstance(v, float)]


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("key", REALS)
def test_every_real_key_refuses_non_finite_values(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=rf"config key '{key}' must be .*got {value!r}"):
        CrowdNavEnv(**{**BASE, key: value})


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"robot_radius_m": 0.0}, r"'robot_radius_m' must be a number > 0, got 0.0"),
        ({"progress_gamma": 1.5}, r"'progress_gamma' must be a number in \(0, 1\], got 1.5"),
        ({"discomfort_scale": -1.0}, r"'discomfort_scale' must be a number >= 0, got -1.0"),
        ({"num_pedestrians": 0}, r"'num_pedestrians' must be an integer >= 1, got 0"),
        ({"synthetic_seed": -1}, r"'synthetic_seed' must be an integer >= 0, got -1"),
        ({"start_goal_distance_m": (5.0, 3.0)}, r"'start_goal_distance_m' must be \(min, max\) with 0 < min <= max"),
        ({"start_goal_distance_m": (5.0, "x")}, r"'start_goal_distance_m' must be \(min, max\) metres: two finite"),
        ({"render_size_px": (10, 640)}, r"'render_size_px' must be \(width, height\) integers >= 16 px"),
        ({"scenes": "zara1"}, r"'scenes' must be a list of recording or scene names, got 'zara1'"),
        ({"predictor": None}, r"predictor=None is not a forecast source"),
        ({"crowd": 3}, r"crowd must be one of auto, replay, synthetic, empty or a Recording, got 3"),
    ],
)
def test_out_of_range_values(kwargs: dict[str, Any], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        CrowdNavEnv(**{**BASE, **kwargs})


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("collision_penalty", math.nan),
        ("discomfort_scale", math.inf),
        ("collision_penalty", "x"),
        ("success_reward", None),
    ],
)
def test_reward_mistakes_fail_at_construction(key: str, value: Any) -> None:
    with pytest.raises(ConfigError, match=rf"config key '{key}' must be a .*number.*, got {value!r}"):
        CrowdNavEnv(**{**BASE, key: value})


def test_yaml_mistakes_name_the_key(tmp_path: Path) -> None:
    path = tmp_path / "env.yaml"
    path.write_text("collision_penalty: .nan\n")
    with pytest.raises(ConfigError, match=r"'collision_penalty' must be a finite number, got nan"):
        CrowdNavEnv(config=str(path), **BASE)
    path.write_text("success_reward: null\n")
    with pytest.raises(ConfigError, match=r"'success_reward' must be a finite number, got None"):
        CrowdNavEnv(config=str(path), **BASE)


def test_predictor_none_never_runs_mesrnn() -> None:
    with pytest.raises(ConfigError, match=r"predictor=None is not a forecast source: pass 'none'"):
        gym.make("CrowdNav-NoPred-v0", predictor=None, crowd="empty")
    env = gym.make("CrowdNav-NoPred-v0", crowd="empty")
    assert env.unwrapped.predictor_name == "none" and "forecasts" not in env.observation_space.spaces
    assert gym.make("CrowdNav-MESRNN-v0", predictor="none", crowd="empty").unwrapped.predictor_name == "none"


CROWD = scripted_recording([np.tile([3.0, 3.0], (100, 1))], name="one")  # 39.6 s of annotations


@pytest.mark.parametrize(
    ("options", "error", "pattern"),
    [
        ("t0", ValueError, r"reset options must be a mapping with keys among recording, t0_s, .*got 't0'"),
        ({"t0": 1.0}, ConfigError, r"unknown reset option key 't0'; valid keys: goal, recording, start, t0_s"),
        ({"t0_s": -100.0}, ValueError, r"'t0_s' must be a finite number of seconds >= 0, got -100.0"),
        ({"t0_s": math.nan}, ValueError, r"'t0_s' must be a finite number of seconds >= 0, got nan"),
        ({"t0_s": "1"}, ValueError, r"'t0_s' must be a finite number of seconds >= 0, got '1'"),
        ({"t0_s": 1e9}, ValueError, r"'t0_s' = 1000000000.0 lies outside the recording 'one': valid \[0, 39.60\) s"),
        ({"time_limit_s": -5}, ValueError, r"'time_limit_s' must be a finite number of seconds > 0, got -5"),
        ({"time_limit_s": 0.0}, ValueError, r"'time_limit_s' must be a finite number of seconds > 0, got 0.0"),
        ({"time_limit_s": math.inf}, ValueError, r"'time_limit_s' must be a finite number of seconds > 0, got inf"),
        (
            {"start": (1.0, 1.0), "goal": (1.0, 1.0)},
            ValueError,
            r"'start' \[1.0, 1.0\] and 'goal' \[1.0, 1.0\] are 0 m",
        ),
        ({"start": (1.0, 2.0, 3.0)}, ValueError, r"'start' must be 2 finite numbers \(metres\), got \(1.0, 2.0, 3.0\)"),
        ({"goal": ("a", "b")}, ValueError, r"'goal' must be 2 finite numbers \(metres\), got \('a', 'b'\)"),
        ({"goal": (0.0, math.nan)}, ValueError, r"'goal' must be 2 finite numbers"),
        ({"recording": "nowhere"}, ValueError, r"unknown recording 'nowhere' for this env; valid: one"),
        ({"recording": 3}, ValueError, r"'recording' must be a recording name, got 3"),
    ],
)
def test_bad_reset_options(options: Any, error: type[Exception], pattern: str) -> None:
    env = CrowdNavEnv(predictor="none", crowd=CROWD)
    with pytest.raises(error, match=pattern):
        env.reset(seed=0, options=options)
    # the env stays usable
    env.reset(seed=0, options={"t0_s": 2.0, "start": (0.0, 0.0), "goal": (6.0, 0.0)})
    env.step(np.zeros(2, dtype=np.float32))
