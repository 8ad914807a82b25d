"""Deprecated: the shared forecast cache moved to :mod:`envs.forecasting.cache`; this module re-exports its public
names, with a DeprecationWarning on import, and will be removed in the next release."""

from __future__ import annotations

import warnings

from envs.forecasting.cache import (
    CACHE_ENV_VAR,
    CARRIED_REVISION,
    CHUNK_FRAMES,
    FORMAT_VERSION,
    PERCEPTION,
    CacheWarning,
    ForecastStore,
    FrameTable,
    TableKey,
    cache_root,
    check_chunk,
    chunk_frames,
    describe,
    num_chunks,
    predictor_fingerprint,
    recording_fingerprint,
)

warnings.warn("envs.forecast_cache is deprecated; import from envs.forecasting.cache", DeprecationWarning, stacklevel=2)

__all__ = [
    "CACHE_ENV_VAR",
    "CARRIED_REVISION",
    "CHUNK_FRAMES",
    "FORMAT_VERSION",
    "PERCEPTION",
    "CacheWarning",
    "ForecastStore",
    "FrameTable",
    "TableKey",
    "cache_root",
    "check_chunk",
    "chunk_frames",
    "describe",
    "num_chunks",
    "predictor_fingerprint",
    "recording_fingerprint",
]
