"""Deprecated: the forecast sources moved to the package :mod:`envs.forecasting`; this module re-exports their
public names, with a DeprecationWarning on import, and will be removed in the next release."""

from __future__ import annotations

import warnings

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
from envs.forecasting.factory import WEIGHTS_HELP, PredictorUnavailableError, load_learned, make_forecast_source
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
