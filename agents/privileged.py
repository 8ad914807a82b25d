"""Deprecated import path of :mod:`agents.planners.privileged` (kept for one release; importing it warns)."""

from __future__ import annotations

import warnings

from agents.planners.privileged import Plan, PlannerStats, PrivilegedPlanner

__all__ = ["Plan", "PlannerStats", "PrivilegedPlanner"]

warnings.warn(
    "agents.privileged is deprecated and will be removed in the next release: import from agents.planners",
    DeprecationWarning,
    stacklevel=2,
)
