"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.claims.compute`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.studies.claims.compute import (  # noqa: F401
    COMMAND,
    LEARNED,
    MODELS,
    POOLED,
    Measured,
    check_headline,
    claims_results,
    compute_claims,
    measure_all,
    tables,
    verdicts,
    weights_for,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.claims.compute")
