"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.claims.declared`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.studies.claims.declared import (  # noqa: F401
    DECLARED,
    ClaimsConfig,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.claims.declared")
