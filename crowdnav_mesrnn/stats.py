"""Deprecated: moved to :mod:`crowdnav_mesrnn.evaluation.statistics`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.evaluation.statistics import (  # noqa: F401
    DEFAULT_BLOCK_LEN,
    DEFAULT_RESAMPLES,
    PairedErrors,
    SeededDifference,
    SeededErrors,
    average_ci,
    block_bootstrap_ci,
    block_bootstrap_replicates,
    block_totals_replicates,
    combine_interval,
    ratio_differences,
    seeded_average_ci,
    seeded_difference_ci,
    verdict,
)

warn_moved(__name__, "crowdnav_mesrnn.evaluation.statistics")
