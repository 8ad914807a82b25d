"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.report` and :mod:`crowdnav_mesrnn.studies.report_render`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.studies.report import (  # noqa: F401
    PAIRS,
    WindowErrors,
    add_claims,
    build_plan_report,
    build_report,
    compare,
    seed_results,
)
from crowdnav_mesrnn.studies.report_render import (  # noqa: F401
    COLS,
    FIGURES,
    LABELS,
    NAMES,
    OPTIONS,
    PLAN_FILE,
    PUBLISHED_SGAN,
    REPRODUCE,
    SECTIONS,
    candidate_confounds,
    ordering,
    render,
    render_candidates_test,
    render_comparisons,
    render_plan,
    render_seeds,
    reproduce_rows,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.report")
