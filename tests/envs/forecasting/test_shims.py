"""The modules that moved into :mod:`envs.forecasting` keep working from their old paths for one release: they
import, warn, and hand out the very objects of the new modules (or, for two functions, their former signatures);
the predictor names of :mod:`envs.config` are asked of the registry, with a warning. The project itself imports
only the new paths."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[3]

#: old module -> (new modules its names come from, a name it must expose)
MOVED = {
    "envs.forecasts": (
        (
            "envs.forecasting.sources",
            "envs.forecasting.window",
            "envs.forecasting.carried",
            "envs.forecasting.factory",
            "envs.forecasting.build",
            "envs.forecasting.resampling",
            "envs.forecasting.cache",
            "envs.forecasting.threads",
        ),
        "make_forecast_source",
    ),
    "envs.forecast_cache": (("envs.forecasting.cache",), "predictor_fingerprint"),
    "envs.uncertainty": (("envs.forecasting.uncertainty",), "make_uncertainty_source"),
}


#: names of envs.config that now belong to the predictor registry
NAMES = {
    f"envs.config.{n}"
    for n in (
        "FORECAST_SOURCES",
        "LEARNED_SOURCES",
        "is_plugin_source",
        "forecast_source_names",
        "check_predictor_name",
    )
}

#: functions that keep their former signature at the old path (adapters onto the new ones)
ADAPTED = {"make_forecast_source", "make_uncertainty_source"}


def fresh_import(name: str) -> object:
    sys.modules.pop(name, None)
    return importlib.import_module(name)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_path_imports_warns_and_exposes_the_same_objects(old: str) -> None:
    new_modules, must_have = MOVED[old]
    with pytest.warns(DeprecationWarning, match=f"{old} is deprecated; import from .*envs.forecasting"):
        module = fresh_import(old)
    names = module.__all__  # type: ignore[attr-defined]
    assert must_have in names
    new = [importlib.import_module(m) for m in new_modules]
    for name in set(names) - ADAPTED:
        homes = [m for m in new if name in vars(m)]
        assert homes, f"{old}.{name} is in none of {new_modules}"
        assert getattr(module, name) is getattr(homes[0], name), f"{old}.{name} is another object"


def test_the_old_paths_expose_every_public_name_they_had() -> None:
    """The names the three modules defined or re-exported before the move."""
    before = {
        "envs.forecasts": "PredictorUnavailableError ForecastModel split_of_recording time_key TrueFuture fill_forward "
        "resample_matrix resample_weights SHARED_RECORDINGS definition_key clear_shared_tables ForecastSource "
        "NoForecast OracleForecast NoisyOracleForecast PredictorForecast CarriedPredictorForecast fork_safe_torch "
        "torch_threads WEIGHTS_HELP load_learned make_forecast_source CACHE_PARTS cache_recordings "
        "build_forecast_cache CHUNK_FRAMES ForecastStore FrameTable TableKey chunk_frames num_chunks "
        "predictor_fingerprint recording_fingerprint",
        "envs.forecast_cache": "FORMAT_VERSION CARRIED_REVISION PERCEPTION CHUNK_FRAMES CACHE_ENV_VAR CacheWarning "
        "cache_root predictor_fingerprint recording_fingerprint TableKey FrameTable ForecastStore chunk_frames "
        "num_chunks check_chunk describe",
        "envs.uncertainty": "UncertaintySource ZeroUncertainty NoisyOracleUncertainty CalibratedUncertainty "
        "calibration_key load_or_fit_calibration make_uncertainty_source",
    }
    for old, names in before.items():
        with pytest.warns(DeprecationWarning):
            module = fresh_import(old)
        assert set(names.split()) <= set(module.__all__), old  # type: ignore[attr-defined]


def test_the_former_signatures_build_the_same_sources(tmp_path: Path) -> None:
    from envs.config import CrowdNavConfig
    from envs.forecasting import factory, uncertainty
    from envs.forecasting.cache import ForecastStore
    from envs.forecasting.sources import NoisyOracleForecast
    from envs.forecasting.window import PredictorForecast

    with pytest.warns(DeprecationWarning):
        old = fresh_import("envs.forecasts")
    with pytest.warns(DeprecationWarning):
        old_unc = fresh_import("envs.uncertainty")
    cv = old.make_forecast_source("cv", [], "hotel", 0.25, 9, False, 0.5, "carried", ForecastStore(tmp_path))  # type: ignore[attr-defined]
    assert isinstance(cv, PredictorForecast) and cv.memory == "window" and cv.store is None
    assert (cv.dt_s, cv.horizon, cv.use_cache) == (0.25, 9, False)
    noisy = old.make_forecast_source("noisy_oracle", [], "hotel", 0.4, 12, True, 0.7)  # type: ignore[attr-defined]
    new = factory.make_forecast_source(CrowdNavConfig(predictor="noisy_oracle", noisy_oracle_ade_m=0.7), [])
    assert isinstance(noisy, NoisyOracleForecast) and isinstance(new, NoisyOracleForecast)
    assert noisy.sigma == new.sigma
    cfg = CrowdNavConfig(predictor="noisy_oracle", forecast_uncertainty_level=0.8, forecast_cache_dir=str(tmp_path))
    radii = old_unc.make_uncertainty_source(noisy, "noisy_oracle", "hotel", 0.8, 0.4, 12, tmp_path)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(radii.per_step, uncertainty.make_uncertainty_source(cfg, new).per_step)
    fake = SimpleNamespace(name="obj", forecast=lambda history, mask: None)
    source = old.make_forecast_source(fake, [], "hotel", 0.4, 12, True, 0.0, "window", ForecastStore(tmp_path))  # type: ignore[attr-defined]
    assert source.default is fake and source.store is not None and source.store.root == tmp_path


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("FORECAST_SOURCES", ("none", "cv", "cv_gaussian", "mesrnn", "srnn", "vlstm", "oracle", "noisy_oracle")),
        ("LEARNED_SOURCES", ("mesrnn", "srnn", "vlstm")),
    ],
)
def test_the_predictor_names_of_env_config_ask_the_registry_with_a_warning(name: str, expected: tuple) -> None:
    import envs.config

    with pytest.warns(DeprecationWarning, match=f"envs.config.{name} is deprecated; use crowdnav_mesrnn.predictors"):
        assert getattr(envs.config, name) == expected
    for function in ("is_plugin_source", "forecast_source_names", "check_predictor_name"):
        with pytest.warns(DeprecationWarning, match=f"envs.config.{function} is deprecated"):
            assert callable(getattr(envs.config, function))
    with pytest.raises(AttributeError, match="has no attribute 'PREDICTORS'"):
        envs.config.PREDICTORS  # noqa: B018


def test_the_project_imports_only_the_new_paths() -> None:
    shims = {ROOT / "envs" / f"{m.rsplit('.', 1)[1]}.py" for m in MOVED}
    offenders = []
    for folder in ("crowdnav_mesrnn", "envs", "agents", "benchmarks", "tests", "examples"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path in shims or path == Path(__file__).resolve():
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    used = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    used = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
                else:
                    continue
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno} {u}" for u in used if u in MOVED or u in NAMES]
    assert not offenders, "imports of deprecated paths: " + ", ".join(offenders)
