"""The predictor registry: the one place that knows the forecast source names, their kinds and how to load them."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.predictors import PluginError

OWN = ("none", "cv", "cv_gaussian", "mesrnn", "srnn", "vlstm", "oracle", "noisy_oracle")


@pytest.fixture
def one_plugin(monkeypatch: pytest.MonkeyPatch) -> str:
    """Exactly one installed plug-in, ``still`` (the real entry points are hidden)."""
    ep = SimpleNamespace(
        name="still",
        value="somewhere.still:Still",
        group=predictors.ENTRY_POINT_GROUP,
        dist=SimpleNamespace(name="still-dist", version="1.0"),
    )
    monkeypatch.setattr(predictors, "_entry_points", lambda: (ep,))
    return "still"


def test_names_in_the_order_shown_to_users_then_the_plugins(one_plugin: str) -> None:
    assert predictors.names(plugins=False) == OWN
    assert predictors.names() == (*OWN, one_plugin)
    assert predictors.names(predictors.PRETRAINED, plugins=False) == ("mesrnn", "srnn", "vlstm")
    assert predictors.names(predictors.PRETRAINED) == ("mesrnn", "srnn", "vlstm")  # no plug-in: another kind
    shipped = predictors.names(predictors.BASELINE, predictors.FITTED_BASELINE, predictors.PRETRAINED, plugins=False)
    assert shipped == ("cv", "cv_gaussian", "mesrnn", "srnn", "vlstm")
    assert predictors.names(predictors.PLUGIN) == (one_plugin,)
    with pytest.raises(PluginError, match="unknown predictor kind 'learned'; valid: none, truth"):
        predictors.names("learned")


def test_every_name_has_one_kind(one_plugin: str) -> None:
    kinds = {name: predictors.kind(name) for name in predictors.names()}
    assert kinds == {
        "none": predictors.NO_FORECAST,
        "cv": predictors.BASELINE,
        "cv_gaussian": predictors.FITTED_BASELINE,
        "mesrnn": predictors.PRETRAINED,
        "srnn": predictors.PRETRAINED,
        "vlstm": predictors.PRETRAINED,
        "oracle": predictors.TRUTH,
        "noisy_oracle": predictors.NOISY_TRUTH,
        one_plugin: predictors.PLUGIN,
    }
    assert set(kinds.values()) == set(predictors.KINDS)
    assert predictors.kind("my_package.models:Factory") == predictors.PLUGIN  # an import path, not imported


@pytest.mark.parametrize("name", ["lstm", "", None, 3, "oracle "])
def test_an_unknown_name_is_an_error_naming_the_valid_ones(one_plugin: str, name: object) -> None:
    valid = f"valid: {', '.join((*OWN, one_plugin))}, or an import path 'package.module:Factory'"
    with pytest.raises(ConfigError, match=f"unknown predictor {name!r}; {valid}"):
        predictors.kind(name)  # type: ignore[arg-type]
    with pytest.raises(PluginError, match=valid):
        predictors.check(name)
    assert not predictors.is_plugin(name) and not predictors.per_split(name)


def test_check_returns_the_name(one_plugin: str) -> None:
    for name in (*predictors.names(), "pkg.mod:Factory"):
        assert predictors.check(name) == name


def test_plugins_and_pretrained_load_per_split(one_plugin: str) -> None:
    per_split = [n for n in predictors.names() if predictors.per_split(n)]
    assert per_split == ["cv_gaussian", "mesrnn", "srnn", "vlstm", one_plugin]
    assert [n for n in predictors.names() if predictors.is_plugin(n)] == [one_plugin]
    assert predictors.per_split("pkg.mod:Factory") and predictors.is_plugin("pkg.mod:Factory")


def test_shipped_and_reserved_names_come_from_the_one_table() -> None:
    shipped = predictors.names(predictors.BASELINE, predictors.FITTED_BASELINE, predictors.PRETRAINED, plugins=False)
    assert tuple(predictors.SHIPPED) == shipped
    assert set(predictors.RESERVED) == set(OWN) - set(shipped)
    assert predictors.RESERVED == ("none", "oracle", "noisy_oracle")


def test_cv_gaussian_is_a_baseline_with_a_distribution_loaded_per_split() -> None:
    from crowdnav_mesrnn.models.cv_gaussian import CvGaussian, load_cv_gaussian

    model = predictors.load("cv_gaussian", "zara1")
    assert isinstance(model, CvGaussian) and model.split == "zara1" and model.has_distribution
    assert model.cache_fingerprint() == load_cv_gaussian("zara1").cache_fingerprint()
    assert model.cache_fingerprint() != predictors.load("cv_gaussian", "eth").cache_fingerprint()
    assert predictors.resolve("cv_gaussian").shipped and predictors.identity_of(model) is None
    with pytest.raises(PluginError, match="needs the split"):
        predictors.load("cv_gaussian")


def test_the_model_lists_ask_the_registry() -> None:
    from crowdnav_mesrnn import models

    with pytest.warns(DeprecationWarning, match="predictors.names"):
        LEARNED_MODELS, MODELS = models.LEARNED_MODELS, models.MODELS
    assert LEARNED_MODELS == predictors.names(predictors.PRETRAINED, plugins=False)
    assert MODELS == ("cv", *LEARNED_MODELS)


@pytest.mark.parametrize("name", ["none", "oracle", "noisy_oracle"])
def test_forecast_sources_that_are_not_predictors_do_not_load(name: str) -> None:
    with pytest.raises(PluginError, match=f"unknown predictor {name!r}"):
        predictors.load(name, "zara1")


def test_the_installed_example_plugin_is_listed() -> None:
    pytest.importorskip("kalman_predictor")
    predictors.refresh()
    assert "kalman" in predictors.names()
    assert predictors.kind("kalman") == predictors.PLUGIN


def test_every_pretrained_name_is_an_architecture_with_weights_files() -> None:
    from crowdnav_mesrnn.models.architecture import MODEL_TYPES
    from crowdnav_mesrnn.models.pretrained import pretrained_path

    assert predictors.names(predictors.PRETRAINED, plugins=False) == tuple(MODEL_TYPES)
    for name in predictors.names(predictors.PRETRAINED, plugins=False):
        assert pretrained_path(name, "zara1").is_file()


def test_check_forecast_accepts_finite_forecasts_of_the_promised_shape_only() -> None:
    where = {"name": "mine", "recording": "walkers", "frame": 7, "time_s": 2.8}
    good = np.zeros((3, 12, 2), np.float32)
    assert predictors.check_forecast(good, expected_shape=(3, 12, 2), **where) is good
    assert predictors.check_forecast([[[0, 0]] * 12], expected_shape=(1, 12, 2), **where).dtype.kind == "i"
    bad = good.copy()
    bad[1, 3] = np.nan
    with pytest.raises(
        predictors.ForecastError,
        match=r"^predictor 'mine' returned non-finite forecasts \(NaN\) for recording 'walkers' at frame 7 "
        r"\(t = 2.80 s\): 1 of 3 pedestrians read \(first: row 1\)",
    ):
        predictors.check_forecast(bad, expected_shape=(3, 12, 2), **where)
    # rows that are not read may hold anything (the protocol's pedestrians absent at the last observed step)
    predictors.check_forecast(bad, expected_shape=(3, 12, 2), rows=np.array([True, False, True]), **where)
    predictors.check_forecast(bad, expected_shape=(3, 12, 2), rows=np.array([0, 2]), **where)
    with pytest.raises(predictors.ForecastError, match=r"1 of 2 pedestrians read \(first: row 1\)"):
        predictors.check_forecast(bad, expected_shape=(3, 12, 2), rows=np.array([1, 2]), **where)
    with pytest.raises(predictors.ForecastError, match=r"returned shape \(3, 12, 2\) .* expected \(3, 8, 2\)"):
        predictors.check_forecast(good, expected_shape=(3, 8, 2), **where)
    with pytest.raises(predictors.ForecastError, match="returned an array of object"):
        predictors.check_forecast(np.array([None, 1], dtype=object), expected_shape=(2,), **where)
    with pytest.raises(predictors.ForecastError, match="returned list, not an array"):
        predictors.check_forecast([[0.0, 0.0], [1.0]], expected_shape=(2, 2), **where)
    assert issubclass(predictors.ForecastError, ValueError)


def test_check_forecast_names_the_frame_of_the_first_bad_row_of_a_batch() -> None:
    batch = np.zeros((4, 12, 2))
    batch[2:, 0, 0] = np.inf
    with pytest.raises(
        predictors.ForecastError, match=r"\(inf\) for recording 'r' at frame 65 \(t = 26.00 s\): 2 of 4"
    ):
        predictors.check_forecast(
            batch,
            name="m",
            expected_shape=(4, 12, 2),
            recording="r",
            frame=np.array([64, 64, 65, 66]),
            time_s=np.array([25.6, 25.6, 26.0, 26.4]),
        )
