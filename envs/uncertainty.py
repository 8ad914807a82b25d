"""Deprecated: forecast uncertainty moved to :mod:`envs.forecasting.uncertainty`; this module re-exports its public
names, with a DeprecationWarning on import, and will be removed in the next release.

:func:`make_uncertainty_source` keeps its former signature here; the new one reads the settings from the env config
(:func:`envs.forecasting.uncertainty.make_uncertainty_source`).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any

from envs.config import CrowdNavConfig
from envs.forecasting import uncertainty
from envs.forecasting.uncertainty import (
    CalibratedUncertainty,
    NoisyOracleUncertainty,
    UncertaintySource,
    ZeroUncertainty,
    calibration_key,
    load_or_fit_calibration,
)

warnings.warn(
    "envs.uncertainty is deprecated; import from envs.forecasting.uncertainty", DeprecationWarning, stacklevel=2
)


def make_uncertainty_source(
    forecaster: Any,
    predictor: Any,
    default_split: str,
    level: float,
    dt_s: float,
    horizon: int,
    cache_dir: Path | None,
    data_dir: str | None = None,
) -> UncertaintySource:
    """Deprecated: :func:`envs.forecasting.uncertainty.make_uncertainty_source` with a config holding these
    settings (``cache_dir``: the forecast cache folder the calibrations are kept in, or None for memory only)."""
    config = dataclasses.replace(
        CrowdNavConfig(),
        split=default_split,
        forecast_uncertainty_level=level,
        dt_s=dt_s,
        horizon_steps=horizon,
        forecast_disk_cache=cache_dir is not None,
        forecast_cache_dir=None if cache_dir is None else str(cache_dir),
        data_dir=data_dir,
        **({"predictor": predictor} if isinstance(predictor, str) else {}),
    )
    return uncertainty.make_uncertainty_source(config, forecaster, None if isinstance(predictor, str) else predictor)


__all__ = [
    "CalibratedUncertainty",
    "NoisyOracleUncertainty",
    "UncertaintySource",
    "ZeroUncertainty",
    "calibration_key",
    "load_or_fit_calibration",
    "make_uncertainty_source",
]
