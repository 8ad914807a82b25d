"""Non-learned policies with Stable-Baselines3's ``predict`` interface.

- :class:`StraightToGoal`: straight to the goal at the preferred speed, slowing down to stop on it.
- :class:`SamplingPlanner`: scores candidate velocities (headings around the goal direction times
  speeds, plus standing still) against the future positions of the observed pedestrians — the
  forecasts the observation carries, or constant-velocity extrapolations of their observed
  velocities when it has none (the ``none`` arm) — and takes the fastest progress that stays clear
  over a few steps of that one velocity. ``candidates="dense"`` (16 headings around the full circle,
  backing away included, x 6 speeds) widens its choice.
- :class:`SearchPlanner`: a layered search over *sequences* of velocities several seconds ahead against
  the same futures, with candidates that back away, replanned every step (the fastest arrival, or the
  closest approach to the goal that stays clear).
- :class:`PrivilegedPlanner` (``make_planner("privileged")``): PRIVILEGED, reads the replay's true future of every
  pedestrian; the ceiling of what is attainable, never a policy.
- :class:`ReactivePrivilegedPlanner` (``make_planner("privileged", reactive=True)``): PRIVILEGED, the ceiling among
  pedestrians who react to the robot (``reaction`` ``pause``, ``orca`` or ``social_force``): a beam search whose
  every candidate step is rolled through the environment's reaction model, so it plans against the pedestrians'
  replies; refuses ``reaction="none"``, where the replay ceiling reads the true future.

All but the privileged ones read only the observation. Each accepts a single observation dict or a
batched one (a leading dimension on every key) and returns ``(actions, None)`` like an SB3 model, so
evaluation (and DAgger, which uses a planner as its teacher) treats planners and learned policies
alike; the scoring and the search are vectorised over the batch, and a batched ``predict`` equals one
``predict`` per observation.

One module each: :mod:`agents.planners.base` (the ``predict`` plumbing, actions from velocities, straight to the
goal), :mod:`agents.planners.sampling`, :mod:`agents.planners.search`, :mod:`agents.planners.privileged` and
:mod:`agents.planners.privileged_reactive`; this package names them (:data:`PLANNERS`, :func:`make_planner`) and
re-exports their public names.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final

from agents.planners.base import (
    StraightToGoal,
    as_env_config,
    go_to_goal,
    region_radii,
    velocities_to_actions,
    velocity_to_action,
)
from agents.planners.privileged import Plan, PlannerStats, PrivilegedPlanner, command_velocities
from agents.planners.privileged_reactive import (
    REACTIVE_OPTIONS,
    ReactivePlan,
    ReactivePlannerStats,
    ReactivePrivilegedPlanner,
    env_velocities,
)
from agents.planners.sampling import (
    CANDIDATE_SETS,
    DEFAULT_HEADINGS_DEG,
    DEFAULT_SPEED_FRACTIONS,
    DENSE_HEADINGS_DEG,
    DENSE_SPEED_FRACTIONS,
    SamplingPlanner,
)
from agents.planners.search import (
    SEARCH_HEADINGS_DEG,
    SEARCH_SPEED_FRACTIONS,
    SearchPlanner,
    lattice_select,
    motion_candidates,
)
from envs.config import CrowdNavConfig

__all__ = [
    "CANDIDATE_SETS",
    "DEFAULT_HEADINGS_DEG",
    "DEFAULT_SPEED_FRACTIONS",
    "DENSE_HEADINGS_DEG",
    "DENSE_SPEED_FRACTIONS",
    "PLANNERS",
    "REACTIVE_OPTIONS",
    "SEARCH_HEADINGS_DEG",
    "SEARCH_SPEED_FRACTIONS",
    "Plan",
    "PlannerStats",
    "PrivilegedPlanner",
    "ReactivePlan",
    "ReactivePlannerStats",
    "ReactivePrivilegedPlanner",
    "SamplingPlanner",
    "SearchPlanner",
    "StraightToGoal",
    "as_env_config",
    "command_velocities",
    "env_velocities",
    "go_to_goal",
    "lattice_select",
    "make_planner",
    "motion_candidates",
    "region_radii",
    "velocities_to_actions",
    "velocity_to_action",
]

#: Names accepted by :func:`make_planner` (``privileged`` reads the replay, or with ``reactive=True`` the reaction
#: model: see :mod:`agents.planners.privileged` and :mod:`agents.planners.privileged_reactive`).
PLANNERS: Final[tuple[str, ...]] = ("straight", "planner", "search", "privileged")


def make_planner(name: str, env_config: CrowdNavConfig | Mapping[str, Any] | None = None, **kwargs: Any) -> Any:
    """A planner by name: ``"straight"`` (:class:`StraightToGoal`), ``"planner"`` (:class:`SamplingPlanner`),
    ``"search"`` (:class:`SearchPlanner`) or ``"privileged"`` (:class:`PrivilegedPlanner`, or with ``reactive=True``
    :class:`ReactivePrivilegedPlanner`; both must be bound to their environments before they act); the other
    ``kwargs`` are passed on."""
    if name == "straight":
        if kwargs:
            raise ValueError(f"the straight-to-goal policy takes no options, got {sorted(kwargs)}")
        return StraightToGoal(env_config)
    if name == "planner":
        return SamplingPlanner(env_config, **kwargs)
    if name == "search":
        return SearchPlanner(env_config, **kwargs)
    if name == "privileged":
        reactive = kwargs.pop("reactive", False)
        if not isinstance(reactive, bool):
            raise ValueError(f"privileged planner option 'reactive': got {reactive!r}; allowed: true or false")
        if not reactive:
            return PrivilegedPlanner(env_config, **kwargs)
        unknown = {k: v for k, v in sorted(kwargs.items()) if k not in {"env", *REACTIVE_OPTIONS}}
        if unknown:
            raise ValueError(
                f"privileged reactive planner option(s) {', '.join(map(repr, unknown))}: got {unknown!r}; allowed: "
                f"{', '.join(REACTIVE_OPTIONS)}"
            )
        return ReactivePrivilegedPlanner(env_config, **kwargs)
    raise ValueError(f"unknown planner {name!r}; valid: {', '.join(PLANNERS)}")
