"""A forecast source is built from the env config and the predictor registry: the kind of the name chooses it, and
predictors are loaded per split from the registry only."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.models import ConstantVelocity
from envs.config import CrowdNavConfig
from envs.forecasting import factory
from envs.forecasting.carried import CarriedPredictorForecast
from envs.forecasting.factory import make_forecast_source
from envs.forecasting.sources import NoForecast, NoisyOracleForecast, OracleForecast
from envs.forecasting.window import PredictorForecast


@pytest.fixture
def loads(
    monkeypatch: pytest.MonkeyPatch, tiny_learned_predictor: Callable, fake_predictor: Callable
) -> list[tuple[str, str | None]]:
    """Every predictor the registry is asked for, answered without weights on disk (constant velocity, a small
    learned predictor, or a stand-in for a plug-in)."""
    asked: list[tuple[str, str | None]] = []

    def load(name: str, split: str | None = None) -> Any:
        asked.append((name, split))
        if name == "cv":
            return ConstantVelocity()
        return tiny_learned_predictor(name) if name in ("mesrnn", "srnn", "vlstm") else fake_predictor(name)

    monkeypatch.setattr(predictors, "load", load)
    monkeypatch.setattr(factory, "_LOADED", {})
    return asked


def test_each_kind_gives_its_source(loads: list, tmp_path: Path) -> None:
    base = CrowdNavConfig(split="hotel", forecast_cache_dir=str(tmp_path), noisy_oracle_ade_m=0.3, horizon_steps=7)
    recordings = ["students001", "crowds_zara01", "synthetic"]

    def make(name: str, **kwargs: Any) -> Any:
        with warnings.catch_warnings():
            warnings.simplefilter("error", DeprecationWarning)  # nothing asks envs.config for predictor names
            return make_forecast_source(CrowdNavConfig(**{**vars(base), "predictor": name, **kwargs}), recordings)

    assert isinstance(make("none"), NoForecast)
    assert type(make("oracle")) is OracleForecast
    noisy = make("noisy_oracle")
    assert isinstance(noisy, NoisyOracleForecast) and (noisy.target_ade_m, noisy.horizon) == (0.3, 7)
    cv = make("cv", forecast_memory="carried")
    assert type(cv) is PredictorForecast and cv.store is None and isinstance(cv.default, ConstantVelocity)
    assert loads == [("cv", None)]
    loads.clear()
    learned = make("srnn")
    assert type(learned) is PredictorForecast and learned.store is not None and learned.store.root == tmp_path
    assert loads == [("srnn", "univ"), ("srnn", "zara1"), ("srnn", "hotel")]  # out of sample; synthetic: config.split
    assert sorted(learned.predictors) == ["crowds_zara01", "students001"] and learned.default is not None
    carried = make("vlstm", forecast_memory="carried", forecast_disk_cache=False)
    assert isinstance(carried, CarriedPredictorForecast) and carried.store is None


def test_a_plugin_loads_per_split(loads: list) -> None:
    source = make_forecast_source(CrowdNavConfig(predictor="pkg.mod:Factory"), ["biwi_eth", "biwi_hotel"])
    assert isinstance(source, PredictorForecast) and source.name == "pkg.mod:Factory"
    assert loads == [("pkg.mod:Factory", "eth"), ("pkg.mod:Factory", "hotel")]


def test_the_name_goes_to_the_registry_once_and_does_not_come_back(
    loads: list, monkeypatch: pytest.MonkeyPatch
) -> None:
    asked: list[str] = []
    kind = predictors.kind
    monkeypatch.setattr(predictors, "kind", lambda name: asked.append(name) or kind(name))
    make_forecast_source(CrowdNavConfig(predictor="mesrnn"), ["crowds_zara02"])
    assert asked == ["mesrnn"] and loads == [("mesrnn", "zara2")]


def test_a_predictor_object_is_used_for_every_recording(fake_predictor: Callable, tmp_path: Path) -> None:
    obj = fake_predictor("mine")
    config = CrowdNavConfig(predictor="none", forecast_cache_dir=str(tmp_path))
    source = make_forecast_source(config, ["biwi_eth"], obj)
    assert isinstance(source, PredictorForecast) and source.default is obj and source.name == "mine"
    assert source.predictors == {} and source.store is not None
    with pytest.raises(
        ConfigError, match="predictor must be one of none, cv, cv_gaussian, mesrnn, srnn, vlstm, oracle"
    ):
        make_forecast_source(config, [], object())  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        (
            {"predictor": "lstm"},
            "unknown predictor 'lstm'; valid: none, cv, cv_gaussian, mesrnn, srnn, vlstm, oracle, noisy_oracle",
        ),
        ({"forecast_memory": "forever"}, "unknown forecast_memory 'forever'; valid: window, carried"),
    ],
)
def test_bad_settings_are_errors_naming_the_valid_ones(changes: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        make_forecast_source(CrowdNavConfig(**changes), [])


def test_missing_weights_name_the_sources_that_need_none(monkeypatch: pytest.MonkeyPatch) -> None:
    def missing(name: str, split: str | None = None) -> Any:
        raise FileNotFoundError(f"no {name}_{split}.pt")

    monkeypatch.setattr(predictors, "load", missing)
    monkeypatch.setattr(factory, "_LOADED", {})
    with pytest.raises(factory.PredictorUnavailableError) as info:
        make_forecast_source(CrowdNavConfig(predictor="mesrnn"), ["biwi_hotel"])
    message = str(info.value)
    assert "the pretrained 'mesrnn' predictor for split 'hotel' (needed to forecast biwi_hotel)" in message
    assert "choose predictor='cv', 'oracle', 'noisy_oracle' or 'none'" in message


def test_cv_gaussian_is_a_window_arm_per_split_keyed_on_its_parameters(tmp_path: Path) -> None:
    """The fitted baseline loads per split like the pretrained (never the held-out scene's fit), always forecasts by
    window (constant velocity has nothing to carry), forecasts constant velocity's points, and its disk cache is keyed
    on ``cache_fingerprint()``, so two splits' parameters never share forecasts."""
    import numpy as np

    from crowdnav_mesrnn.models.cv_gaussian import CvGaussian
    from envs.forecasting.cache import predictor_fingerprint

    config = CrowdNavConfig(predictor="cv_gaussian", split="hotel", forecast_cache_dir=str(tmp_path))
    for memory in ("window", "carried"):
        source = make_forecast_source(
            replace(config, forecast_memory=memory), ["biwi_eth", "crowds_zara01", "synthetic"]
        )
        assert type(source) is PredictorForecast and source.store is not None and source.name == "cv_gaussian"
    models = {rec: m for rec, m in source.predictors.items()}
    assert {rec: m.split for rec, m in models.items()} == {"biwi_eth": "eth", "crowds_zara01": "zara1"}
    assert isinstance(source.default, CvGaussian) and source.default.split == "hotel"
    digests = {predictor_fingerprint(m) for m in (*models.values(), source.default)}
    assert digests == {m.cache_fingerprint() for m in (*models.values(), source.default)} and len(digests) == 3
    rng = np.random.default_rng(0)
    history, mask = rng.normal(size=(8, 4, 2)).astype(np.float32), np.ones((8, 4), bool)
    assert np.array_equal(models["biwi_eth"].forecast(history, mask), ConstantVelocity().forecast(history, mask))
