"""Options for the agents: time penalty, time left in the observation, episodes near pedestrians, crowd
density, the train/val time split and the episode metrics."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data import load_recording
from envs.crowd_nav import CrowdNavEnv
from envs.episodes import crowd_near_path
from envs.recordings import scripted_recording


def _standing(env: CrowdNavEnv, options: dict[str, Any] | None = None, seed: int = 0) -> list[tuple]:
    obs, info = env.reset(seed=seed, options=options)
    out = [(obs, 0.0, False, False, info)]
    done = False
    while not done:
        obs, reward, terminated, truncated, info = env.step(np.zeros(2, dtype=np.float32))
        out.append((obs, reward, terminated, truncated, info))
        done = terminated or truncated
    return out


def test_time_penalty_is_a_reward_component() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty", time_penalty=-0.05, time_limit_factor=0.5)
    steps = _standing(env, {"start": (0.0, 0.0), "goal": (4.0, 0.0)})
    for _, reward, *_, info in steps[1:]:
        assert info["reward_components"]["time"] == -0.05
        assert reward == pytest.approx(sum(info["reward_components"].values()))
    assert CrowdNavEnv(predictor="none", crowd="empty").config.time_penalty == 0.0


@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
def test_time_left_is_appended_to_robot(kinematics: str) -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty", observe_time_left=True, kinematics=kinematics)
    size = 7 if kinematics == "unicycle" else 5
    assert env.observation_space["robot"].shape == (size,)
    steps = _standing(env, {"start": (0.0, 0.0), "goal": (2.0, 0.0)})
    left = [s[0]["robot"][-1] for s in steps]
    n = len(steps) - 1
    assert steps[-1][3] and n == env.episode.max_steps  # type: ignore[union-attr]
    np.testing.assert_allclose(left, 1.0 - np.arange(n + 1) / n, atol=1e-6)
    assert all(s[0] in env.observation_space for s in steps)
    assert CrowdNavEnv(predictor="none", crowd="empty").observation_space["robot"].shape == (4,)


def test_crowd_density_counts_pedestrians_near_the_segment() -> None:
    # three pedestrians standing 1 m, 5 m and 7 m from the segment (0,0)-(8,0); the 5 m one leaves after 10 steps
    crowd = scripted_recording(
        [np.tile([4.0, 1.0], (50, 1)), np.tile([4.0, -5.0], (10, 1)), np.tile([-7.0, 0.0], (50, 1))]
    )
    density, near = crowd_near_path(crowd, 0.0, 7.6, np.zeros(2), np.array([8.0, 0.0]), 6.0)
    # annotations 0..19 (0 .. 7.6 s): 2 pedestrians at the first 10, 1 at the next 10
    assert near == 2 and density == pytest.approx(1.5)
    env = CrowdNavEnv(predictor="none", crowd=crowd)
    _, info = env.reset(seed=0, options={"t0_s": 0.0, "start": (0.0, 0.0), "goal": (8.0, 0.0), "time_limit_s": 7.6})
    assert info["crowd_density"] == pytest.approx(1.5) and info["pedestrians_near_path"] == 2


def test_crowd_density_counts_empty_frames_as_empty() -> None:
    """ETH/UCY files list only frames with pedestrians: a gap in the frame numbers is time when nobody was
    there, and counts as zero (averaging over the listed frames only called a mostly empty episode crowded)."""
    from dataclasses import replace

    crowd = scripted_recording([np.tile([4.0, 1.0], (40, 1))])  # one pedestrian near the path at every frame
    keep = np.r_[0:10, 30:40]  # frames 10..29 (8 s) have no rows in the file: the scene is empty then
    gappy = replace(crowd, frames=crowd.frames[keep], positions=crowd.positions[keep], present=crowd.present[keep])
    density, near = crowd_near_path(gappy, 0.0, 15.6, np.zeros(2), np.array([8.0, 0.0]), 6.0)
    assert near == 1 and density == pytest.approx(20 / 40)
    # an episode inside the gap sees nobody; one running past the recording's end counts the time after it as empty
    assert crowd_near_path(gappy, 5.2, 4.0, np.zeros(2), np.array([8.0, 0.0]), 6.0) == (0.0, 0)
    # frames 30..39, then 10 empty annotation times after the recording's end
    density, _ = crowd_near_path(gappy, 12.0, 7.6, np.zeros(2), np.array([8.0, 0.0]), 6.0)
    assert density == pytest.approx(10 / 20)


def test_episode_metrics_only_under_their_own_key() -> None:
    crowd = scripted_recording([np.tile([2.0, 1.0], (80, 1))])
    env = CrowdNavEnv(predictor="none", crowd=crowd, time_limit_factor=1.0)
    steps = _standing(env, {"t0_s": 0.0, "start": (0.0, 0.0), "goal": (4.0, 0.0)})
    last = steps[-1][4]
    assert "episode" not in last
    metrics = last["episode_metrics"]
    assert metrics["mean_visible_pedestrians"] == 1.0
    assert metrics["crowd_density"] == steps[0][4]["crowd_density"] == 1.0
    assert metrics["pedestrians_near_path"] == 1
    assert metrics["l"] == len(steps) - 1 and metrics["r"] == pytest.approx(sum(s[1] for s in steps))
    assert all("episode_metrics" not in s[4] for s in steps[:-1])


def test_require_pedestrians_keeps_episodes_near_people(data_dir: Path) -> None:
    common = {"data_dir": str(data_dir), "split": "hotel", "part": "test"}
    plain = CrowdNavEnv(predictor="none", **common)
    empty = sum(plain.reset(seed=seed)[1]["pedestrians_near_path"] == 0 for seed in range(200))
    assert empty > 0  # hotel has long annotation gaps
    arms = [CrowdNavEnv(predictor=p, require_pedestrians=True, **common) for p in ("none", "cv", "oracle")]
    for seed in range(30):
        infos = [env.reset(seed=seed)[1] for env in arms]
        assert infos[0]["pedestrians_near_path"] >= 1 and infos[0]["crowd_density"] > 0
        keys = ("recording", "t0_s", "start", "goal", "time_limit_s", "crowd_density")
        assert all([i[k] for k in keys] == [infos[0][k] for k in keys] for i in infos)
    with pytest.raises(RuntimeError, match="require_pedestrians"):
        CrowdNavEnv(predictor="none", crowd="empty", require_pedestrians=True).reset(seed=0)


@pytest.mark.parametrize("part", ["train", "val"])
def test_episode_time_split(data_dir: Path, part: str) -> None:
    env = CrowdNavEnv(predictor="none", data_dir=str(data_dir), split="eth", part="train", episode_time=part)
    for seed in range(40):
        _, info = env.reset(seed=seed)
        end = float(load_recording(info["recording"], data_dir=data_dir).times_s()[-1])
        cut = 0.8 * end
        t0, t1 = info["t0_s"], info["t0_s"] + info["time_limit_s"]
        if part == "val":
            assert cut - 1e-9 <= t0 and t1 <= end + 1e-9
        else:
            assert t1 <= cut + 1e-9
    rec = env.recordings[0].name
    bad = 10.0 if part == "val" else float(env.recordings[0].times_s()[-1]) - 5.0
    with pytest.raises(ValueError, match=rf"'t0_s' = {bad!r} lies outside the '{part}' episode time"):
        env.reset(seed=0, options={"recording": rec, "t0_s": bad})


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"time_penalty": float("nan")}, r"'time_penalty' must be a finite number, got nan"),
        ({"observe_time_left": 1}, r"'observe_time_left' must be true or false"),
        ({"require_pedestrians": "yes"}, r"'require_pedestrians' must be true or false"),
        ({"episode_time": "test"}, r"unknown episode_time 'test'; valid: all, train, val"),
        ({"val_fraction": 1.0}, r"'val_fraction' must be a number in \(0, 1\), got 1.0"),
        ({"val_fraction": 0}, r"'val_fraction' must be a number in \(0, 1\), got 0"),
    ],
)
def test_new_keys_are_validated(kwargs: dict[str, Any], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        CrowdNavEnv(predictor="none", crowd="empty", **kwargs)
