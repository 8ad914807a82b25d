"""Deprecated: the forecast sources moved to the package :mod:`envs.forecasting`; this module re-exports their
public names, with a DeprecationWarning on import, and will be removed in the next release.

:func:`make_forecast_source` keeps its former signature here (a name or object and eight settings); the new one
builds a source from the env config (:func:`envs.forecasting.factory.make_forecast_source`).
"""

from __future__ import annotations

import dataclasses
import warnings

from envs.config import CrowdNavConfig
from envs.forecasting import factory
from envs.forecasting.build import CACHE_PARTS, build_forecast_cache, cache_recordings
from envs.forecasting.cache import (
    CHUNK_FRAMES,
    SHARED_RECORDINGS,
    ForecastStore,
    FrameTable,
    TableKey,
    chunk_frames,
    clear_shared_tables,
    definition_key,
    num_chunks,
    predictor_fingerprint,
    recording_fingerprint,
)
from envs.forecasting.carried import CarriedPredictorForecast
from envs.forecasting.factory import WEIGHTS_HELP, PredictorUnavailableError, load_learned
from envs.forecasting.resampling import resample_matrix, resample_weights, time_key
from envs.forecasting.sources import (
    ForecastModel,
    ForecastSource,
    NoForecast,
    NoisyOracleForecast,
    OracleForecast,
    TrueFuture,
    fill_forward,
    split_of_recording,
)
from envs.forecasting.threads import fork_safe_torch, torch_threads
from envs.forecasting.window import PredictorForecast

warnings.warn(
    "envs.forecasts is deprecated; import from the package envs.forecasting (its modules sources, window, carried, "
    "factory, build, resampling, cache and threads)",
    DeprecationWarning,
    stacklevel=2,
)


def make_forecast_source(
    predictor: str | ForecastModel,
    recordings: list[str],
    default_split: str,
    dt_s: float,
    horizon: int,
    cache: bool,
    noisy_oracle_ade_m: float,
    memory: str = "window",
    store: ForecastStore | None = None,
) -> ForecastSource:
    """Deprecated: :func:`envs.forecasting.factory.make_forecast_source` with a config holding these settings
    (``store``: the disk cache in its folder, or None for none)."""
    config = dataclasses.replace(
        CrowdNavConfig(),
        split=default_split,
        dt_s=dt_s,
        horizon_steps=horizon,
        cache_forecasts=cache,
        noisy_oracle_ade_m=noisy_oracle_ade_m,
        forecast_memory=memory,
        forecast_disk_cache=store is not None,
        forecast_cache_dir=None if store is None else str(store.root),
        **({"predictor": predictor} if isinstance(predictor, str) else {}),
    )
    return factory.make_forecast_source(config, recordings, None if isinstance(predictor, str) else predictor)


__all__ = [
    "CACHE_PARTS",
    "CHUNK_FRAMES",
    "SHARED_RECORDINGS",
    "WEIGHTS_HELP",
    "CarriedPredictorForecast",
    "ForecastModel",
    "ForecastSource",
    "ForecastStore",
    "FrameTable",
    "NoForecast",
    "NoisyOracleForecast",
    "OracleForecast",
    "PredictorForecast",
    "PredictorUnavailableError",
    "TableKey",
    "TrueFuture",
    "build_forecast_cache",
    "cache_recordings",
    "chunk_frames",
    "clear_shared_tables",
    "definition_key",
    "fill_forward",
    "fork_safe_torch",
    "load_learned",
    "make_forecast_source",
    "num_chunks",
    "predictor_fingerprint",
    "recording_fingerprint",
    "resample_matrix",
    "resample_weights",
    "split_of_recording",
    "time_key",
    "torch_threads",
]
