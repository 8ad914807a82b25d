"""Deprecated: forecast uncertainty moved to :mod:`envs.forecasting.uncertainty`; this module re-exports its public
names, with a DeprecationWarning on import, and will be removed in the next release."""

from __future__ import annotations

import warnings

from envs.forecasting.uncertainty import (
    CalibratedUncertainty,
    NoisyOracleUncertainty,
    UncertaintySource,
    ZeroUncertainty,
    calibration_key,
    load_or_fit_calibration,
    make_uncertainty_source,
)

warnings.warn(
    "envs.uncertainty is deprecated; import from envs.forecasting.uncertainty", DeprecationWarning, stacklevel=2
)

__all__ = [
    "CalibratedUncertainty",
    "NoisyOracleUncertainty",
    "UncertaintySource",
    "ZeroUncertainty",
    "calibration_key",
    "load_or_fit_calibration",
    "make_uncertainty_source",
]
