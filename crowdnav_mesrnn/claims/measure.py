"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.claims.measure`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.studies.claims.measure import (  # noqa: F401
    FORECAST_KEYS,
    MOTIONS,
    bin_label,
    colliding_pairs,
    density_bin,
    measure_batch,
    measure_windows,
    motion_types,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.claims.measure")
