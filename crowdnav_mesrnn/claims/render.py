"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.claims.render`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.studies.claims.render import (  # noqa: F401
    MODEL_ORDER,
    NAMES,
    render_claims,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.claims.render")
