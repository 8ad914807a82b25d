"""Predictors as plug-ins: registration by entry point or import path, use in every forecast arm, cache identity."""

from __future__ import annotations

import os
import sys
import textwrap
import tomllib
from pathlib import Path
from types import SimpleNamespace

import gymnasium
import numpy as np
import pytest

import crowdnav_mesrnn  # noqa: F401  (registers the env ids)
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.predictors import ENTRY_POINT_GROUP, SHIPPED, PluginError, identity_of, load, registered, resolve

ROOT = Path(__file__).resolve().parents[2]

PLUGIN_SOURCE = '''
import numpy as np


class StandStill:
    """Everyone stays where last seen: forecasts that differ from every shipped predictor's."""

    name = "standstill"
    obs_len = 8
    pred_len = 12

    def __init__(self, split=None):
        self.split = split

    def forecast(self, history, mask):
        t_last = np.where(mask, np.arange(mask.shape[0])[:, None], 0).max(axis=0)
        last = history[t_last, np.arange(history.shape[1])]
        return np.repeat(last[:, None, :], self.pred_len, axis=1).astype(np.float32)


def broken(split=None):
    return object()


class NoSplit:
    def __init__(self):
        pass
'''


@pytest.fixture
def plugin_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """An importable module ``standstill_plugin`` (a fresh name per test run) holding a plug-in factory."""
    (tmp_path / "standstill_plugin.py").write_text(textwrap.dedent(PLUGIN_SOURCE))
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("standstill_plugin", None)
    return "standstill_plugin"


def fake_entry_points(monkeypatch: pytest.MonkeyPatch, *entries: tuple[str, str, str, str]) -> None:
    """Installed entry points in our group: ``(name, target, distribution, version)`` each."""
    eps = tuple(
        SimpleNamespace(name=n, value=v, group=ENTRY_POINT_GROUP, dist=SimpleNamespace(name=d, version=ver))
        for n, v, d, ver in entries
    )
    monkeypatch.setattr(predictors, "_entry_points", lambda: eps)
    monkeypatch.setattr(predictors, "_WARNED", set())  # their warnings are given afresh


def test_shipped_models_register_in_pyproject_exactly_as_the_fallback_table() -> None:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert meta["project"]["entry-points"][ENTRY_POINT_GROUP] == SHIPPED
    assert set(registered()) >= set(SHIPPED)
    assert all(registered()[n].shipped for n in SHIPPED)


def test_entry_point_plugin_loads_by_name(monkeypatch: pytest.MonkeyPatch, plugin_module: str) -> None:
    fake_entry_points(monkeypatch, ("still", f"{plugin_module}:StandStill", "still-dist", "1.0"))
    assert predictors.plugin_names() == ("still",)
    model = load("still", split="univ")
    assert model.split == "univ" and identity_of(model) is not None
    history = np.zeros((8, 2, 2), np.float32)
    history[:, 0] = [[k, 0] for k in range(8)]
    out = model.forecast(history, np.ones((8, 2), bool))
    assert out.shape == (2, 12, 2) and np.all(out[0] == [7, 0])


def test_identity_changes_with_version_and_source(monkeypatch: pytest.MonkeyPatch, plugin_module: str) -> None:
    from envs.forecasting.cache import predictor_fingerprint

    fake_entry_points(monkeypatch, ("still", f"{plugin_module}:StandStill", "still-dist", "1.0"))
    a = load("still", "zara1")
    fake_entry_points(monkeypatch, ("still", f"{plugin_module}:StandStill", "still-dist", "1.1"))
    b = load("still", "zara1")
    assert identity_of(a) != identity_of(b)
    fa, fb = predictor_fingerprint(a), predictor_fingerprint(b)
    assert fa is not None and fb is not None and fa != fb  # weightless plug-ins are disk-cached, keyed per version
    # an unregistered object of the same class is not disk-cached (nothing identifies it)
    assert predictor_fingerprint(type(a)()) is None


def test_import_path_works_without_registration(plugin_module: str) -> None:
    spec = resolve(f"{plugin_module}:StandStill")
    assert spec.target == f"{plugin_module}:StandStill" and spec.distribution is None
    assert load(f"{plugin_module}:StandStill").name == "standstill"


@pytest.mark.parametrize(
    ("entries", "match"),
    [
        ((("none", "x:Y", "d", "1"),), r"plug-in 'none' = 'x:Y' of the distribution 'd': its name is reserved"),
        ((("a:b", "x:Y", "d", "1"),), r"plug-in 'a:b' = 'x:Y' of the distribution 'd': its name contains ':'"),
        (
            (("mesrnn", "x:Y", "d", "1"),),
            "'x:Y' of the distribution 'd': it would replace the shipped predictor 'mesrnn'",
        ),
    ],
)
def test_bad_registrations_are_skipped_with_a_warning_and_the_others_kept(
    monkeypatch: pytest.MonkeyPatch, entries: tuple, match: str, plugin_module: str
) -> None:
    fake_entry_points(monkeypatch, *entries, ("still", f"{plugin_module}:StandStill", "still-dist", "1.0"))
    with pytest.warns(predictors.PluginWarning, match=match):
        specs = registered()
    assert predictors.plugin_names() == ("still",) and load("still", "eth").name == "standstill"
    assert specs["mesrnn"].shipped and "none" not in specs and "a:b" not in specs


def test_a_name_registered_twice_is_skipped_and_an_error_naming_both_when_asked_for(
    monkeypatch: pytest.MonkeyPatch, plugin_module: str
) -> None:
    fake_entry_points(
        monkeypatch,
        ("dup", "a:B", "d1", "1"),
        ("dup", "c:D", "d2", "1"),
        ("still", f"{plugin_module}:StandStill", "still-dist", "1.0"),
    )
    with pytest.warns(predictors.PluginWarning, match=r"'dup': it is registered by several plug-ins, 'a:B' \(d1\) and"):
        assert predictors.plugin_names() == ("still",)
    with pytest.raises(
        PluginError, match=r"'dup' is ambiguous: .*'a:B' \(d1\) and 'c:D' \(d2\); uninstall all but one"
    ):
        load("dup")


def test_unknown_names_and_broken_plugins_are_clear_errors(plugin_module: str) -> None:
    with pytest.raises(PluginError, match=r"unknown predictor 'nope'; valid: .*mesrnn.*package\.module:Factory"):
        load("nope")
    with pytest.raises(PluginError, match="cannot import 'missing_mod_xyz:F'"):
        load("missing_mod_xyz:F")
    with pytest.raises(PluginError, match="no forecast"):
        load(f"{plugin_module}:broken")
    with pytest.raises(PluginError, match="must accept a keyword argument split="):
        load(f"{plugin_module}:NoSplit")


def test_gymnasium_make_and_config_accept_a_plugin(
    monkeypatch: pytest.MonkeyPatch, plugin_module: str, data_dir: Path
) -> None:
    from crowdnav_mesrnn.config import ConfigError

    fake_entry_points(monkeypatch, ("still", f"{plugin_module}:StandStill", "still-dist", "1.0"))
    env = gymnasium.make("CrowdNav-MESRNN-v0", predictor="still", split="zara1", part="test")
    try:
        _, info = env.reset(seed=0)
        source = env.unwrapped.forecaster
        assert source.name == "still" and info["predictor"] == "still"
        model = source.predictor_for("crowds_zara01")
        assert type(model).__name__ == "StandStill" and model.split == "zara1"  # the held-out scene's split
        env.step(env.action_space.sample())
    finally:
        env.close()
    with pytest.raises(ConfigError, match=r"unknown predictor 'stil'; valid: none, cv, .*still, or an import path"):
        gymnasium.make("CrowdNav-MESRNN-v0", predictor="stil")


def test_agents_evaluate_accepts_a_plugin(
    monkeypatch: pytest.MonkeyPatch, plugin_module: str, data_dir: Path, tmp_path: Path
) -> None:
    from agents.evaluation.cli import main as evaluate_main

    fake_entry_points(monkeypatch, ("still", f"{plugin_module}:StandStill", "still-dist", "1.0"))
    argv = ["planner", "--predictor", "still", "--split", "zara1", "--episodes", "2", "--n-envs", "1"]
    assert evaluate_main([*argv, "--out", str(tmp_path / "ev"), "--no-progress"]) == 0
    assert (tmp_path / "ev" / "episodes.csv").is_file()


# ---------------------------------------------------------------------------- the example package


def _kalman_installed() -> bool:
    predictors.refresh()
    return "kalman" in registered()


@pytest.fixture
def kalman() -> None:
    if not _kalman_installed():
        if os.environ.get("CI"):
            pytest.fail("CI installs examples/kalman_predictor; its entry point 'kalman' is missing")
        pytest.skip("examples/kalman_predictor is not installed (pip install ./examples/kalman_predictor)")


def test_example_plugin_is_registered_and_used_by_gymnasium_make(kalman: None, data_dir: Path) -> None:
    spec = registered()["kalman"]
    assert spec.distribution == "crowdnav-kalman-predictor" and not spec.shipped
    env = gymnasium.make("CrowdNav-MESRNN-v0", predictor="kalman", split="zara1", part="test")
    try:
        env.reset(seed=0)
        assert env.unwrapped.forecaster.name == "kalman"
        env.step(env.action_space.sample())
    finally:
        env.close()


def test_example_kalman_filter_follows_a_straight_line_and_grows_uncertain(kalman: None) -> None:
    model = load("kalman")
    history = np.zeros((8, 2, 2), np.float32)
    history[:, 0] = np.stack([0.4 * np.arange(8), 0.1 * np.arange(8)], axis=1)  # constant velocity (0.4, 0.1)/step
    mask = np.ones((8, 2), bool)
    mask[:6, 1] = False  # pedestrian 1 seen twice, at rest
    history[6:, 1] = [2.0, 3.0]
    mean, cov = model.forecast_distribution(history, mask)
    truth = history[-1, 0] + np.arange(1, 13)[:, None] * np.array([0.4, 0.1])
    assert np.abs(mean[0] - truth).max() < 0.05  # a filter converges to the true velocity on noise-free data
    assert np.allclose(mean[1], [2.0, 3.0], atol=1e-4)
    var = cov[:, :, 0, 0]
    assert np.all(np.diff(var, axis=1) > 0)  # uncertainty grows with the horizon
    assert var[1, -1] > var[0, -1]  # and is larger for the pedestrian seen twice
