"""Deprecated: moved to :mod:`crowdnav_mesrnn.training.head_fit`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.training.head_fit import (  # noqa: F401
    HEAD_KEYS,
    SHORTCUT_NOTE,
    HeadFitConfig,
    HeadRows,
    fit_head,
    fit_head_on_rows,
    gaussian_network,
    head_rows,
    metres_offset,
    validation_nll_m,
)

warn_moved(__name__, "crowdnav_mesrnn.training.head_fit")
