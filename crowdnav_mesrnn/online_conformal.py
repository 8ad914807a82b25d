"""Deprecated: moved to :mod:`crowdnav_mesrnn.uncertainty.online_conformal`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.uncertainty.online_conformal import (  # noqa: F401
    EXPERT_INTERVAL,
    GAMMA_GRID,
    GAMMA_RULES,
    GAMMA_TOLERANCE,
    METHODS,
    REVEAL_RULES,
    Feedback,
    OnlineResult,
    Stream,
    aggregate_thresholds,
    choose_gamma,
    expert_rates,
    feedback_stream,
    online_coverage,
    online_for_split,
    scene_streams,
    track_thresholds,
    unit_radius,
    validation_deviation,
    window_clock,
)

warn_moved(__name__, "crowdnav_mesrnn.uncertainty.online_conformal")
