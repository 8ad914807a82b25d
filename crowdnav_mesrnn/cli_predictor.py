"""Deprecated: moved to :mod:`crowdnav_mesrnn.cli.predictor`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.cli.predictor import (  # noqa: F401
    add_parser,
)

warn_moved(__name__, "crowdnav_mesrnn.cli.predictor")
