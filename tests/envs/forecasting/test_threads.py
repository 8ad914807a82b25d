"""Forecasts computed on first use: on one torch thread (small batched ops: more threads only contend), and with a
labelled progress bar when a chunk takes over a second (the first demo without data was silent for 86 s)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.threads import FORECAST_THREADS
from envs.recordings import scripted_recording


class ThreadsSeen:
    """A predictor recording torch's thread count at every call (optionally sleeping, to be slow)."""

    name, obs_len, pred_len = "threads-seen", 8, 12

    def __init__(self, sleep_s: float = 0.0) -> None:
        self.sleep_s = sleep_s
        self.threads: list[int] = []

    def cache_fingerprint(self) -> str:
        return f"threads-seen-{self.sleep_s}"

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        self.threads.append(torch.get_num_threads())
        time.sleep(self.sleep_s)
        return np.repeat(history[-1][:, None], self.pred_len, axis=1)


def _crowd(frames: int = 80, name: str | None = None) -> Any:
    rng = np.random.default_rng(0)
    paths = [np.cumsum(rng.normal(0.0, 0.2, (frames, 2)), axis=0) + 4.0 + 2.0 * k for k in range(3)]
    return scripted_recording(paths, name=name or f"progress-{frames}")


@pytest.mark.parametrize("cache", [True, False])
def test_forecasts_run_torch_on_one_thread_and_leave_the_setting_as_it_was(cache: bool, tmp_path: Any) -> None:
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        predictor = ThreadsSeen()
        env = CrowdNavEnv(predictor=predictor, crowd=_crowd(), cache_forecasts=cache, forecast_cache_dir=str(tmp_path))
        env.reset(seed=0)
        env.step(np.zeros(2, dtype=np.float32))
        assert predictor.threads and set(predictor.threads) == {1}
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_slow_chunk_shows_a_labelled_progress_bar(capsys: pytest.CaptureFixture[str], tmp_path: Any) -> None:
    predictor = ThreadsSeen(sleep_s=0.025)  # 64 frames: 1.6 s, over the bar's 1 s delay
    env = CrowdNavEnv(predictor=predictor, crowd=_crowd(), forecast_cache_dir=str(tmp_path))
    env.precompute_forecasts()
    err = capsys.readouterr().err
    assert "threads-seen forecasts of progress-80, frames 0-63 (computed once, then cached)" in err
    assert "64/64" in err
    fast = CrowdNavEnv(predictor=ThreadsSeen(), crowd=_crowd(70), forecast_cache_dir=str(tmp_path))
    fast.precompute_forecasts()
    assert "forecasts of" not in capsys.readouterr().err, "no bar for what takes under a second"


def test_building_the_cache_computes_on_one_thread_and_restores_the_callers(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Any
) -> None:
    from envs.forecasting import build, factory

    seen = ThreadsSeen()
    monkeypatch.setattr(factory, "load_learned", lambda name, split, needed_for: seen)
    monkeypatch.setattr(factory, "_LOADED", {})
    monkeypatch.setattr(
        "crowdnav_mesrnn.data.recordings.load_recording", lambda name, part="all_data", data_dir=None: _crowd(70, name)
    )
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # a caller's own setting (`forecasts build --threads 2` used to set it)
    try:
        build.build_forecast_cache("mesrnn", "zara1", "test", cache_dir=str(tmp_path), progress=False)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert seen.threads and set(seen.threads) == {FORECAST_THREADS} == {1}


@pytest.mark.slow
def test_the_cache_build_writes_the_same_bytes_whatever_the_callers_threads(
    data_dir: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """MESRNN on two threads moves forecasts by up to ~1e-5 m: a build on the caller's two threads wrote other bits
    than the environment computes online (and than a build on one thread)."""
    from crowdnav_mesrnn.data.recordings import load_recording
    from envs.forecasting import build

    full = load_recording("crowds_zara01", data_dir=data_dir)
    head = replace(full, frames=full.frames[:64], positions=full.positions[:64], present=full.present[:64])
    monkeypatch.setattr("crowdnav_mesrnn.data.recordings.load_recording", lambda name, part, data_dir: head)
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            build.build_forecast_cache(
                "mesrnn", "zara1", "test", cache_dir=str(tmp_path / str(threads)), progress=False
            )
    finally:
        torch.set_num_threads(before)
    one, two = sorted((tmp_path / "1").rglob("*.npz")), sorted((tmp_path / "2").rglob("*.npz"))
    assert len(one) == 1 and [p.name for p in one] == [p.name for p in two]
    for a, b in zip(one, two, strict=True):
        assert a.read_bytes() == b.read_bytes(), f"{b.name} differs from the one-thread build"
