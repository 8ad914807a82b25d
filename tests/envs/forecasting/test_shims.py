"""The modules that moved into :mod:`envs.forecasting` keep working from their old paths for one release: they
import, warn, and hand out the very objects of the new modules; the project itself imports only the new paths."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

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
    for name in names:
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
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno} {u}" for u in used if u in MOVED]
    assert not offenders, "imports of deprecated paths: " + ", ".join(offenders)
