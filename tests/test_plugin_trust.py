"""Installed plug-ins as real distributions (``dist-info`` folders on ``sys.path``, as pip lays them out): any file of
one keys its cached forecasts (issue 27 item 3), and one bad registration spoils no other plug-in (item 5)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

import crowdnav_mesrnn  # noqa: F401 (registers the env ids)
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.cli import main
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting import factory
from envs.recordings import scripted_recording

MODEL = '''
import json
from pathlib import Path

import numpy as np

PARAMS = Path(__file__).with_name("params.json")


class Drift:
    """Everyone keeps drifting by ``params.json``'s ``step`` (metres per annotation step) along x."""

    name, obs_len, pred_len = "drift", 8, 12

    def __init__(self, split=None):
        self.step = json.loads(PARAMS.read_text())["step"]

    def forecast(self, history, mask):
        t_last = np.where(mask, np.arange(mask.shape[0])[:, None], 0).max(axis=0)
        last = history[t_last, np.arange(history.shape[1])]
        k = np.arange(1, self.pred_len + 1)[None, :, None]
        return (last[:, None, :] + k * np.array([self.step, 0.0])).astype(np.float32)
'''

PACKAGE = {
    "drift_plugin/__init__.py": "from drift_plugin.model import Drift\n",
    "drift_plugin/model.py": MODEL,
    "drift_plugin/params.json": '{"step": 0.25}\n',
    "drift_plugin/unused.py": "# a module the factory does not import\nVALUE = 1\n",
}


def crowd() -> Any:
    paths = [np.stack([np.linspace(1.0, 9.0, 70), np.full(70, y)], axis=1) for y in (2.0, 3.0, 4.0)]
    return scripted_recording(paths, name="drifters")


def forecasts_of(name: str, cache_dir: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[dict[str, int], np.ndarray]:
    """A fresh process's view: the plug-in loaded anew, its forecasts of :func:`crowd` from the disk cache or
    computed; returns the source's counters and the first chunk's forecasts."""
    monkeypatch.setattr(factory, "_LOADED", {})
    env = CrowdNavEnv(predictor=name, crowd=crowd(), forecast_cache_dir=str(cache_dir))
    env.precompute_forecasts()
    source = env.forecaster
    counts = {"computed": source.chunks_computed, "loaded": source.chunks_loaded}
    return counts, source.chunk(env.recordings[0], 0).forecasts


@pytest.mark.parametrize("record", [True, False], ids=["installed", "editable"])
def test_editing_any_file_of_a_plugin_recomputes_its_forecasts(
    install_dist: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, record: bool
) -> None:
    """``installed``: pip's RECORD lists the files; ``editable``: it lists none of them (an editable install)."""
    site = install_dist("drift-plugin", "1.0", {"drift": "drift_plugin:Drift"}, PACKAGE, record=record)
    first, fc = forecasts_of("drift", tmp_path, monkeypatch)
    assert first == {"computed": 2, "loaded": 0}
    assert forecasts_of("drift", tmp_path, monkeypatch)[0] == {"computed": 0, "loaded": 2}  # nothing changed

    # a parameter file, edited in place (same size): the factory's module is untouched
    (site / "drift_plugin/params.json").write_text('{"step": 0.75}\n')
    again, changed = forecasts_of("drift", tmp_path, monkeypatch)
    assert again == {"computed": 2, "loaded": 0}
    assert np.abs(changed - fc).max() > 1.0  # the old forecasts were not served
    # another module of the package, which the factory does not even import
    (site / "drift_plugin/unused.py").write_text("# a module the factory does not import\nVALUE = 2\n")
    assert forecasts_of("drift", tmp_path, monkeypatch)[0] == {"computed": 2, "loaded": 0}
    assert forecasts_of("drift", tmp_path, monkeypatch)[0] == {"computed": 0, "loaded": 2}


def test_the_identity_follows_the_record_of_a_reinstall_and_the_version(install_dist: Any) -> None:
    """A reinstall with other files (the same version) writes another RECORD: another identity."""
    install_dist("drift-plugin", "1.0", {"drift": "drift_plugin:Drift"}, PACKAGE)
    one = predictors.resolve("drift").identity()
    install_dist("drift-plugin", "1.0", {"drift": "drift_plugin:Drift"}, {**PACKAGE, "drift_plugin/extra.txt": "x"})
    two = predictors.resolve("drift").identity()
    install_dist("drift-plugin", "1.1", {"drift": "drift_plugin:Drift"}, {**PACKAGE, "drift_plugin/extra.txt": "x"})
    three = predictors.resolve("drift").identity()
    assert len({one, two, three}) == 3


def test_the_shipped_predictors_identities_ignore_the_files_of_the_package() -> None:
    """The shipped predictors are keyed by their weights (``predictor_fingerprint``), never by this digest: the keys of
    committed results stay (``tests/envs/forecasting/test_cache.py`` pins them)."""
    from envs.forecasting.cache import predictor_fingerprint

    mesrnn = predictors.load("mesrnn", "zara1")
    assert predictors.identity_of(mesrnn) is None
    assert predictor_fingerprint(mesrnn) == "3b3452a7956ddac106fb46fdadc57a9b652e760ec3a339d10ffa34c895044ca3"
    assert predictor_fingerprint(predictors.load("cv")) is None  # defined by its code: never on disk


# ---------------------------------------------------------------------------- one bad plug-in


STILL = """
import numpy as np


class Still:
    name, obs_len, pred_len = "still", 8, 12

    def __init__(self, split=None):
        pass

    def forecast(self, history, mask):
        t_last = np.where(mask, np.arange(mask.shape[0])[:, None], 0).max(axis=0)
        last = history[t_last, np.arange(history.shape[1])]
        return np.repeat(last[:, None, :], self.pred_len, axis=1).astype(np.float32)
"""


def test_a_package_taking_a_reserved_or_shipped_name_is_skipped_and_the_others_work(
    install_dist: Any, data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    install_dist("greedy-names", "0.1", {"oracle": "greedy:Still", "mesrnn": "greedy:Still"}, {"greedy.py": STILL})
    install_dist("good-still", "1.0", {"goodstill": "good_still:Still"}, {"good_still.py": STILL})
    with pytest.warns(predictors.PluginWarning) as caught:
        names = predictors.names()
    messages = sorted(str(w.message) for w in caught)
    assert len(messages) == 2
    assert (
        "plug-in 'mesrnn' = 'greedy:Still' of the distribution 'greedy-names': it would replace the shipped"
        in (messages[0])
    )
    assert "plug-in 'oracle' = 'greedy:Still' of the distribution 'greedy-names': its name is reserved" in messages[1]
    assert "goodstill" in names and names.count("oracle") == names.count("mesrnn") == 1
    assert predictors.kind("oracle") == predictors.TRUTH and predictors.registered()["mesrnn"].shipped

    env = gymnasium.make("CrowdNav-MESRNN-v0", predictor="goodstill", split="zara1", part="test")
    try:
        _, info = env.reset(seed=0)
        assert info["predictor"] == "goodstill"
    finally:
        env.close()
    out = tmp_path / "bench"
    argv = ["bench", "goodstill", "--splits", "eth", "--no-planner", "--resamples", "100", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    assert json.loads((out / "report.json").read_text())["predictor"] == "goodstill"
