"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.plotting`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.studies.plotting import (  # noqa: F401
    COLOURS,
    plot_window,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.plotting")
