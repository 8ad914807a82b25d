"""Fixtures of the environment tests: a stand-in learned predictor and small scripted crowds."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest


@pytest.fixture(scope="session", autouse=True)
def forecast_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Every env test writes its forecast cache into a fresh temporary folder (never ``~/.cache``)."""
    from envs.forecasting.cache import CACHE_ENV_VAR

    path = tmp_path_factory.mktemp("forecast-cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CACHE_ENV_VAR, str(path))
        yield path


class FakeLearnedPredictor:
    """Implements the predictor interface like a learned social model would, without weights.

    Constant velocity plus a pull of 0.05 x (mean of the others' last positions - own) per step, so the
    forecast of a pedestrian depends on everyone passed in the batch. Optionally records its inputs.
    """

    obs_len = 8
    pred_len = 12

    def __init__(self, name: str = "fake", record: bool = False) -> None:
        self.name = name
        self.record = record
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        history = np.asarray(history, dtype=np.float32)
        mask = np.asarray(mask, dtype=bool)
        assert history.shape == (self.obs_len, mask.shape[1], 2)
        if self.record:
            self.calls.append((history.copy(), mask.copy()))
        last = history[-1]
        vel = np.where((mask[-1] & mask[-2])[:, None], history[-1] - history[-2], 0.0)
        now = mask[-1]
        others = last[now].mean(axis=0) if now.any() else np.zeros(2, dtype=np.float32)
        pull = 0.05 * (others - last)
        k = np.arange(1, self.pred_len + 1, dtype=np.float32)[None, :, None]
        return (last[:, None] + k * (vel + pull)[:, None]).astype(np.float32)


@pytest.fixture
def fake_predictor() -> Callable[..., FakeLearnedPredictor]:
    """Factory of :class:`FakeLearnedPredictor` objects."""
    return FakeLearnedPredictor


def make_tiny_learned_predictor(model: str = "mesrnn", seed: int = 0) -> Any:
    """A small randomly initialised :class:`~crowdnav_mesrnn.models.learned.LearnedPredictor` (no weights on disk)."""
    import torch

    from crowdnav_mesrnn.data.normalization import MinMax
    from crowdnav_mesrnn.models.architecture import ModelConfig
    from crowdnav_mesrnn.models.learned import LearnedPredictor
    from crowdnav_mesrnn.models.structural_rnn import StructuralRNN

    torch.manual_seed(seed)
    cfg = ModelConfig(model=model, node_hidden=16, node_embed=8, edge_hidden=8, edge_embed=4)
    return LearnedPredictor(StructuralRNN(cfg), MinMax((0.0, 0.0), (20.0, 20.0)))


@pytest.fixture
def tiny_learned_predictor() -> Callable[..., Any]:
    """Factory of small random learned predictors (they have ``online(num_slots)``)."""
    return make_tiny_learned_predictor


def go_to_goal(obs: dict[str, np.ndarray], cfg: Any) -> np.ndarray:
    """Straight to the goal at the preferred speed, arriving in one step when closer than a step.

    Holonomic: the velocity scaled by the preferred speed. Unicycle: turn towards the goal (at most the
    maximum turn rate over one step) and drive at the speed times the cosine of the heading error.
    (A local scripted policy, so these tests do not depend on the agents package.)
    """
    offset = np.asarray(obs["robot"][:2], dtype=np.float64)
    dist = float(np.hypot(offset[0], offset[1]))
    if dist < 1e-9:
        return np.zeros(2, dtype=np.float32)
    speed = min(cfg.robot_pref_speed_mps, dist / cfg.dt_s)
    velocity = offset / dist * speed
    if cfg.kinematics == "holonomic":
        return np.clip(velocity / cfg.robot_pref_speed_mps, -1.0, 1.0).astype(np.float32)
    heading = math.atan2(float(obs["robot"][5]), float(obs["robot"][4]))
    err = math.remainder(math.atan2(velocity[1], velocity[0]) - heading, 2 * math.pi)
    turn = float(np.clip(err / (cfg.robot_max_turn_rate_radps * cfg.dt_s), -1.0, 1.0))
    forward = speed / cfg.robot_pref_speed_mps * max(math.cos(err), 0.0)
    return np.array([min(forward, 1.0), turn], dtype=np.float32)


@pytest.fixture
def goal_seeker() -> Callable[[dict[str, np.ndarray], Any], np.ndarray]:
    """:func:`go_to_goal`."""
    return go_to_goal


def run_episode(
    env: Any, policy: Callable[[Any], Any], seed: int | None = None, options: dict | None = None
) -> list[tuple]:
    """Run one episode; returns ``[(obs, reward, terminated, truncated, info), ...]`` with the reset first."""
    obs, info = env.reset(seed=seed, options=options)
    out: list[tuple] = [(obs, 0.0, False, False, info)]
    done = False
    while not done:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        out.append((obs, reward, terminated, truncated, info))
        done = terminated or truncated
    return out


@pytest.fixture
def episode_runner() -> Callable[..., list[tuple]]:
    return run_episode


def run_in_lockstep(cached: Any, online: Any, options: list[dict], atol: float = 0.0) -> int:
    """Drive two environments with go-to-goal through the same seeded episodes, asserting identical
    observations and forecasts at every step (forecasts to ``atol`` metres: batched and single predictor
    calls may round float32 differently); returns the number of forecast rows compared."""
    compared = 0
    for k, opts in enumerate(options):
        a_obs, _ = cached.reset(seed=k, options=opts)
        b_obs, _ = online.reset(seed=k, options=opts)
        done = False
        while not done:
            for key in b_obs:
                if key == "forecasts" and atol:
                    np.testing.assert_allclose(a_obs[key], b_obs[key], rtol=0, atol=atol)
                else:
                    np.testing.assert_array_equal(a_obs[key], b_obs[key])
            fa, fb = cached.last_forecasts, online.last_forecasts
            assert (fa is None) == (fb is None)
            if fa is not None:
                np.testing.assert_allclose(fa, fb, rtol=0, atol=atol)
                compared += len(fa)
            a_obs, _, term, trunc, _ = cached.step(go_to_goal(a_obs, cached.config))
            b_obs, *_ = online.step(go_to_goal(b_obs, online.config))
            done = term or trunc
    return compared


@pytest.fixture
def lockstep() -> Callable[..., int]:
    return run_in_lockstep
