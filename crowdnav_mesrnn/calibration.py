"""Deprecated: moved to :mod:`crowdnav_mesrnn.uncertainty.calibration` and :mod:`crowdnav_mesrnn.uncertainty.conformal`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.uncertainty.calibration import (  # noqa: F401
    Forecaster,
    average_fields,
    calibrate_model,
    calibration_from_scores,
    calibration_scores,
    coverage_fields,
    fit_calibration,
    forecaster_for,
    format_calibration,
)
from crowdnav_mesrnn.uncertainty.conformal import (  # noqa: F401
    CALIBRATION_FORMAT,
    LEVELS,
    SCORES,
    SIGMA_FLOOR_M,
    Calibration,
    Coverage,
    ErrorModel,
    conformal_quantile,
    conformal_thresholds,
    gaussians_of,
    level_key,
    measure_coverage,
    region_scores,
)

warn_moved(__name__, "crowdnav_mesrnn.uncertainty.calibration")
