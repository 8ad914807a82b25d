"""Before forecasts are computed, one line on stderr says what, about how long on this machine and where they are
cached (the Python API included: ``agents.evaluation.evaluate`` builds the cache with ``progress=False``)."""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest

import envs.forecasting.build as build
from envs.forecasting.window import PredictorForecast

#: A fast predictor plug-in (constant velocity written out), loaded by import path: disk-cached like a learned one.
PLUGIN = """
import numpy as np


class Fast:
    name = "fast"
    obs_len = 8
    pred_len = 12

    def forecast(self, history, mask):
        velocity = history[-1] - history[-2]
        return history[-1][:, None, :] + velocity[:, None, :] * np.arange(1, 13)[None, :, None]


def factory(split=None):
    return Fast()
"""


@pytest.fixture
def fast_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "fast_forecasts.py").write_text(textwrap.dedent(PLUGIN), encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    return "fast_forecasts:factory"


def test_a_cold_build_says_what_how_long_and_where_before_the_work(
    data_dir: Path, fast_plugin: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    real_num_chunks = build.num_chunks
    monkeypatch.setattr(build, "num_chunks", lambda rec: min(2, real_num_chunks(rec)))  # a slice: two chunks
    real_chunk = PredictorForecast.chunk
    said_before_work: list[str] = []

    def chunk(self: PredictorForecast, recording: object, c: int) -> object:
        said_before_work.append(capsys.readouterr().err)  # what stderr held when this piece of work began
        return real_chunk(self, recording, c)  # type: ignore[arg-type]

    monkeypatch.setattr(PredictorForecast, "chunk", chunk)
    cache = tmp_path / "cache"
    summary = build.build_forecast_cache(fast_plugin, "zara1", "test", cache_dir=str(cache), progress=False)
    assert summary["computed"] == summary["chunks"] == 2
    notice = said_before_work[0]
    assert re.fullmatch(
        rf"computing {re.escape(fast_plugin)} forecasts for 1 recording \(crowds_zara01: 2 of 2 chunks; 128 frames, "
        rf"[\d,]+ pedestrian forecasts\), about \d+ (s|min|h) on this machine now; cached afterwards in "
        rf"{re.escape(str(cache))}\n",
        notice,
    ), notice
    assert all(not err for err in said_before_work[1:])  # one line, not one per chunk

    said_before_work.clear()
    again = build.build_forecast_cache(fast_plugin, "zara1", "test", cache_dir=str(cache), progress=False)
    assert again["loaded"] == 2 and again["computed"] == 0
    assert "".join(said_before_work) + capsys.readouterr().err == ""  # nothing to compute, nothing said


def test_the_timing_probe_is_not_counted_as_forecast_frames(data_dir: Path, fast_plugin: str, tmp_path: Path) -> None:
    from crowdnav_mesrnn.data.recordings import load_recording
    from envs.config import CrowdNavConfig
    from envs.forecasting.factory import make_forecast_source

    config = CrowdNavConfig(predictor=fast_plugin, split="zara1", forecast_cache_dir=str(tmp_path))
    source = make_forecast_source(config, ["crowds_zara01"])
    assert isinstance(source, PredictorForecast)
    rec = load_recording("crowds_zara01")
    busy = [i for i in range(64) if rec.present[i].any()][:3]
    seconds = build.seconds_per_frame(source, [(rec, i) for i in busy])
    assert seconds is not None and seconds >= 0 and source.calls == 0
