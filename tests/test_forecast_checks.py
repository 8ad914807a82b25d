"""Every forecast is checked where it enters the environment, the disk cache and ``bench``: numbers of the promised
shape, finite where read (issue 27 item 2). The error names the predictor, the recording and the frame."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

import crowdnav_mesrnn  # noqa: F401 (registers the env ids)
from crowdnav_mesrnn.predictors import ForecastError
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.cache import ForecastStore, FrameTable, TableKey
from envs.recordings import scripted_recording

PLUGIN = '''
import numpy as np


class Broken:
    """Stands still, but spoils its forecasts in one of several ways (``how``)."""

    obs_len, pred_len = 8, 12
    how = "nan"

    def __init__(self, split=None):
        self.name = "broken-" + self.how

    def forecast(self, history, mask):
        t_last = np.where(mask, np.arange(mask.shape[0])[:, None], 0).max(axis=0)
        out = np.repeat(history[t_last, np.arange(history.shape[1])][:, None], self.pred_len, axis=1)
        if self.how == "nan":
            out[mask[-1], 5] = np.nan  # every pedestrian read gets a NaN
        elif self.how == "inf":
            out[np.flatnonzero(mask[-1])[-1:], -1, 0] = np.inf
        elif self.how == "shape":
            out = out[:, :-1]
        elif self.how == "unread":  # NaN only where the protocol does not read: allowed
            out[~mask[-1]] = np.nan
        return out


class Nan(Broken):
    how = "nan"


class Inf(Broken):
    how = "inf"


class Shape(Broken):
    how = "shape"


class Unread(Broken):
    how = "unread"
'''

ENTRY_POINTS = {"nanny": "broken_plugin:Nan", "infy": "broken_plugin:Inf", "shapey": "broken_plugin:Shape"}
MESSAGES = {
    "nanny": r"predictor 'nanny \(broken-nan\)' returned non-finite forecasts \(NaN\) for recording 'crowds_zara01' "
    r"at frame \d+ \(t = [\d.]+ s\)",
    "infy": r"predictor 'infy \(broken-inf\)' returned non-finite forecasts \(inf\) for recording 'crowds_zara01' at "
    r"frame \d+",
    "shapey": r"predictor 'shapey \(broken-shape\)' returned shape \(\d+, 11, 2\) for recording 'crowds_zara01' at "
    r"frame \d+ \(t = [\d.]+ s\), expected \(\d+, 12, 2\)",
}


@pytest.fixture
def broken_plugins(install_dist: Any) -> None:
    """The plug-ins of :data:`ENTRY_POINTS`, installed as a package would be (registered names)."""
    entry_points = {**ENTRY_POINTS, "unread": "broken_plugin:Unread"}
    install_dist("broken-forecasts", "1.0", entry_points, {"broken_plugin/__init__.py": PLUGIN})


def npz_files(root: Path) -> list[Path]:
    return sorted(root.rglob("*.npz"))


@pytest.mark.parametrize("cache", [True, False], ids=["cached", "online"])
@pytest.mark.parametrize("name", list(ENTRY_POINTS))
def test_the_env_refuses_a_plugin_forecast_naming_it_the_recording_and_the_frame(
    data_dir: Path, tmp_path: Path, broken_plugins: None, name: str, cache: bool
) -> None:
    env = gymnasium.make(
        "CrowdNav-MESRNN-v0",
        predictor=name,
        split="zara1",
        part="test",
        cache_forecasts=cache,
        forecast_cache_dir=str(tmp_path),
    )
    try:
        with pytest.raises(ForecastError, match=MESSAGES[name]):
            env.reset(seed=0)
            for _ in range(50):  # the first forecast read (online: when a pedestrian is first perceived)
                env.step(np.zeros(2, np.float32))
    finally:
        env.close()
    assert npz_files(tmp_path) == []  # no chunk of them was written


def test_a_plugin_may_leave_the_rows_it_is_not_read_for_unfinished(
    data_dir: Path, tmp_path: Path, broken_plugins: None
) -> None:
    env = gymnasium.make(
        "CrowdNav-MESRNN-v0", predictor="unread", split="zara1", part="test", forecast_cache_dir=str(tmp_path)
    )
    obs, _ = env.reset(seed=0)
    for _ in range(5):
        obs, *_ = env.step(np.zeros(2, np.float32))
        assert np.isfinite(obs["forecasts"]).all()
    env.close()
    assert npz_files(tmp_path)  # its forecasts are cached like any plug-in's


@pytest.mark.parametrize("name", list(ENTRY_POINTS))
def test_building_the_cache_refuses_it_and_writes_nothing(
    data_dir: Path, tmp_path: Path, broken_plugins: None, name: str
) -> None:
    from envs.forecasting import build_forecast_cache

    with pytest.raises(ForecastError, match=MESSAGES[name]):
        build_forecast_cache(name, "zara1", "test", cache_dir=str(tmp_path), progress=False)
    assert npz_files(tmp_path) == []


class OnlineNan:
    """A predictor object whose carried (online) forecaster returns NaN from the 20th annotation on."""

    name, obs_len, pred_len = "online-nan", 8, 12

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        return np.repeat(history[-1][:, None], self.pred_len, axis=1)

    def online(self, num_slots: int) -> Any:
        outer = self

        class Forecaster:
            seen = 0
            last = np.zeros((num_slots, 2))

            def observe(self, positions: np.ndarray, present: np.ndarray) -> None:
                self.seen += 1
                self.last = np.where(present[:, None], positions, self.last)

            def forecast(self) -> np.ndarray:
                out = np.repeat(self.last[:, None], outer.pred_len, axis=1)
                return out * np.nan if self.seen > 20 else out

        return Forecaster()


@pytest.mark.parametrize("cache", [True, False], ids=["cached", "online"])
def test_the_carried_source_checks_the_online_forecaster(tmp_path: Path, cache: bool) -> None:
    paths = [np.stack([np.linspace(1.0, 9.0, 60), np.full(60, y)], axis=1) for y in (2.0, 3.0, 4.0)]
    crowd = scripted_recording(paths, name="walkers")
    env = CrowdNavEnv(
        predictor=OnlineNan(), crowd=crowd, forecast_memory="carried", cache_forecasts=cache,
        forecast_cache_dir=str(tmp_path),
    )  # fmt: skip
    with pytest.raises(
        ForecastError,
        match=r"predictor 'online-nan \(online forecaster\)' returned non-finite forecasts \(NaN\) for recording "
        r"'walkers' at frame 20 \(t = 8.00 s\)",
    ):
        env.precompute_forecasts() if cache else [env.forecaster.frame_forecasts(crowd, i) for i in range(60)]


def test_the_disk_cache_never_writes_a_chunk_that_is_not_finite(tmp_path: Path) -> None:
    store = ForecastStore(tmp_path)
    key = TableKey("mine", "0" * 64, "walkers", "1" * 64, "window", 8, 12)
    good = np.zeros((5, 12, 2), np.float32)
    table = FrameTable(np.array([0, 2, 2, 5]), np.array([0, 1, 0, 1, 2]), good)
    assert store.save(key, 1, table) is not None
    bad = good.copy()
    bad[3, 7, 1] = np.nan  # the third frame of the table: chunk 2 holds frames 128-191
    with pytest.raises(ForecastError, match=r"predictor 'mine' .*\(NaN\) for recording 'walkers' at frame 130"):
        store.save(key, 2, FrameTable(table.offsets, table.columns, bad))
    with pytest.raises(ForecastError, match=r"returned shape \(5, 11, 2\) .*expected \(5, 12, 2\)"):
        store.save(key, 3, FrameTable(table.offsets, table.columns, good[:, :11]))
    assert [p.name.endswith("-c0001.npz") for p in npz_files(tmp_path)] == [True]


def test_bench_refuses_it_naming_the_window(data_dir: Path, tmp_path: Path, broken_plugins: None) -> None:
    from agents.bench.metrics import predictor_metrics

    with pytest.raises(
        ForecastError,
        match=r"predictor 'nanny \(broken-nan\)' returned non-finite forecasts \(NaN\) for recording 'biwi_eth' at frame \d+ "
        r"\(the window's first observed step\)",
    ):
        predictor_metrics("nanny", splits=("eth",), out_dir=tmp_path, n_resamples=10)
    assert npz_files(tmp_path) == []  # no per-window sums were kept
