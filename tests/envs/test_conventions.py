"""Gymnasium and Stable-Baselines3 conventions: monitoring wrappers own ``info["episode"]``, and rendering
``rgb_array`` needs no pygame (``human`` mode says which extra to install)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import RecordEpisodeStatistics
from stable_baselines3.common.monitor import Monitor

import crowdnav_mesrnn  # noqa: F401  (registers the ids)

REPO = Path(__file__).resolve().parents[2]
METRICS = {"outcome", "navigation_time_s", "path_ratio", "min_gap_m", "crowd_density", "mean_visible_pedestrians"}


def _episodes(env: gym.Env, n: int) -> list[dict]:
    """Final infos of ``n`` episodes of a standing robot (short time limit)."""
    finals = []
    env.reset(seed=0)
    while len(finals) < n:
        _, _, terminated, truncated, info = env.step(np.zeros(2, dtype=np.float32))
        if terminated or truncated:
            finals.append(info)
            env.reset()
    return finals


def test_record_episode_statistics_wraps_the_env() -> None:
    env = RecordEpisodeStatistics(gym.make("CrowdNav-NoPred-v0", crowd="synthetic", time_limit_factor=0.5))
    finals = _episodes(env, 3)
    for info in finals:
        assert set(info["episode"]) == {"r", "l", "t"}
        assert METRICS <= set(info["episode_metrics"])
        assert info["episode"]["l"] == info["episode_metrics"]["l"]
        assert np.isclose(info["episode"]["r"], info["episode_metrics"]["r"])
    assert len(env.return_queue) == 3


def test_sb3_monitor_keeps_the_env_metrics(tmp_path: Path) -> None:
    env = Monitor(
        gym.make("CrowdNav-CV-v0", crowd="synthetic", time_limit_factor=0.5),
        filename=str(tmp_path / "run"),
        info_keywords=("episode_metrics",),
    )
    finals = _episodes(env, 2)
    for info in finals:
        assert set(info["episode"]) >= {"r", "l", "t"}
        assert METRICS <= set(info["episode_metrics"])
        assert info["episode"]["l"] == info["episode_metrics"]["steps"]
    env.close()
    lines = (tmp_path / "run.monitor.csv").read_text().splitlines()
    assert lines[1].startswith("r,l,t,episode_metrics") and len(lines) == 4 and "outcome" in lines[2]


NO_PYGAME = """
import sys
sys.modules["pygame"] = None  # as if the render extra were not installed
import numpy as np, gymnasium, crowdnav_mesrnn
from gymnasium.error import DependencyNotInstalled
from gymnasium.utils.env_checker import check_env
env = gymnasium.make("CrowdNav-CV-v0", crowd="synthetic", render_mode="rgb_array", render_size_px=(160, 120))
check_env(env.unwrapped)
env.reset(seed=0)
frame = env.render()
print(frame.shape, frame.dtype, env.metadata["render_modes"], "pygame" in sys.modules and sys.modules["pygame"] is not None)
try:
    gymnasium.make("CrowdNav-CV-v0", crowd="synthetic", render_mode="human")
except DependencyNotInstalled as exc:
    print("human:", exc)
"""


def test_rgb_array_without_pygame_and_human_mode_names_the_extra() -> None:
    out = subprocess.run(
        [sys.executable, "-c", NO_PYGAME], capture_output=True, text=True, timeout=120, cwd=REPO, check=True
    )
    lines = out.stdout.strip().splitlines()
    assert lines[0] == "(120, 160, 3) uint8 ['rgb_array'] False"
    assert lines[1].startswith("human: ") and "crowdnav-mesrnn[render]" in lines[1]
