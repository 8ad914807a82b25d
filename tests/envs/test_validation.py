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
        ({"num_pedestrians": 0}, r"'num_pedestrians' must be an integer in \[1, 1000\], got 0"),
        ({"synthetic_seed": -1}, r"'synthetic_seed' must be an integer >= 0, got -1"),
        ({"start_goal_distance_m": (5.0, 3.0)}, r"'start_goal_distance_m' must be \(min, max\) with 0 < min <= max"),
        ({"start_goal_distance_m": (5.0, "x")}, r"'start_goal_distance_m' must be \(min, max\) metres: two finite"),
        ({"render_size_px": (10, 640)}, r"'render_size_px' must be \(width, height\) integers in \[16, 4096\] px"),
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
        (
            {"t0": 1.0},
            ConfigError,
            r"unknown reset option key 't0'; did you mean 't0_s'\? \(valid keys: goal, .*time_limit_s\)",
        ),
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


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        # sizes that used to fail deep inside numpy or Python (or hang) instead of naming the key
        ({"dt_s": 1e300}, r"'dt_s' = 1e\+300 and 'physics_dt_s' = 0.1 give .* substeps per control step; at most 1000"),
        ({"physics_dt_s": 1e-9}, r"'dt_s' = 0.4 and 'physics_dt_s' = 1e-09 give .* substeps per control step"),
        ({"num_pedestrians": 10**30}, r"'num_pedestrians' must be an integer in \[1, 1000\], got 10{30}"),
        ({"horizon_steps": 1e300}, r"'horizon_steps' must be an integer in \[1, 1000\], got 1000000"),
        ({"render_trail_steps": 10**30}, r"'render_trail_steps' must be an integer in \[1, 10000\]"),
        ({"render_size_px": (16, 10**9)}, r"'render_size_px' must be \(width, height\) integers in \[16, 4096\] px"),
        ({"synthetic_duration_s": 1e-6}, r"'synthetic_duration_s' must be a number >= 1, got 1e-06"),
        # a start-goal distance the goal tolerance already covers: every episode would succeed at once
        (
            {"start_goal_distance_m": (0.2, 0.25)},
            r"'start_goal_distance_m' = \(0.2, 0.25\) must start above 'goal_tolerance_m' = 0.3",
        ),
        ({"goal_tolerance_m": 1e300}, r"'start_goal_distance_m' = \(6.0, 12.0\) must start above 'goal_tolerance_m'"),
    ],
)
def test_absurd_sizes_are_refused_naming_the_key(kwargs: dict[str, Any], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        CrowdNavEnv(**{**BASE, **kwargs})


@pytest.mark.parametrize(
    ("config", "kwargs", "pattern"),
    [
        ({"predictor": math.nan}, {}, r"unknown predictor nan; valid: none, cv"),
        ({"predictor": "x"}, {}, r"unknown predictor 'x'"),
        ({"collision_penalty": math.nan}, {"collision_penalty": -5.0}, r"'collision_penalty' must be a finite number"),
        ({"num_pedestrians": "10"}, {"num_pedestrians": 5}, r"'num_pedestrians' must be an integer in \[1, 1000\]"),
    ],
)
def test_config_values_shadowed_by_keywords_are_still_checked(
    config: dict[str, Any], kwargs: dict[str, Any], pattern: str
) -> None:
    """The id's ``predictor`` (and any keyword) overrides ``config``, but nonsense in ``config`` is still refused
    rather than silently dropped (``gym.make("CrowdNav-MESRNN-v0", config={"predictor": nan})`` ran MESRNN)."""
    with pytest.raises(ConfigError, match=pattern):
        gym.make("CrowdNav-MESRNN-v0", config={"crowd": "empty", **config}, **kwargs)
    # a valid config value overridden by a keyword is fine (one config drives every arm)
    env = gym.make("CrowdNav-NoPred-v0", config={"crowd": "empty", "predictor": "mesrnn", "collision_penalty": -3.0})
    assert env.unwrapped.predictor_name == "none"


def test_rendering_survives_extreme_scales() -> None:
    """No hang (a 1 m grid at 1e-9 px/m drew 6e11 lines) and no Pillow overflow (radii of 1e300 px)."""
    import time

    for kwargs in (
        {"render_px_per_m": 1e-9},
        {"render_px_per_m": 1e300},
        {"sensor_range_m": 1e30},
        {"predictor": "noisy_oracle", "noisy_oracle_ade_m": 1e300, "crowd": "synthetic"},
    ):
        env = CrowdNavEnv(**{**BASE, **kwargs}, render_mode="rgb_array", render_size_px=(64, 48))
        env.reset(seed=0)
        started = time.process_time()
        for _ in range(3):
            frame = env.render()
            assert frame is not None and frame.shape == (48, 64, 3)
            env.step(np.zeros(2, dtype=np.float32))
        assert time.process_time() - started < 5.0, kwargs


@pytest.mark.parametrize("key", ["start", "goal"])
def test_a_lone_start_or_goal_outside_the_scene_is_named(key: str) -> None:
    """Only one of start/goal given: the other is placed inside the scene, so the given one must lie there too;
    it used to fail after 500 tries with 'could not place a start and goal ... lower start_goal_distance_m'."""
    env = CrowdNavEnv(predictor="none", crowd=CROWD)
    with pytest.raises(ValueError, match=rf"reset option '{key}' \[1000.0, 3.0\] lies outside the scene of 'one'"):
        env.reset(seed=0, options={key: (1000.0, 3.0)})
    env.reset(seed=0, options={"start": (1000.0, 3.0), "goal": (1006.0, 3.0)})  # both given: anywhere


def test_boolean_points_are_refused() -> None:
    env = CrowdNavEnv(predictor="none", crowd=CROWD)
    with pytest.raises(
        ValueError, match=r"reset option 'start' must be 2 finite numbers \(metres\), got \(True, False\)"
    ):
        env.reset(seed=0, options={"start": (True, False)})
