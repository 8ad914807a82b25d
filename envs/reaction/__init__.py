"""Pedestrians who react to the robot while keeping their real trajectories ("replay-then-model", issue 28).

Pure numpy (and ``pyrvo`` for ORCA): no gymnasium, no pymunk. One :class:`ReactiveCrowd` per episode moves the
pedestrians step by step from their recording, the robot's position and velocity; :class:`DisturbanceMetrics`
measures what the robot did to them. See ``docs/reaction.md``.

Models (:data:`REACTION_MODELS`): ``none`` (the recording), ``pause`` (wait before contact, resume time-shifted),
``orca`` and ``social_force`` (react when the robot is near, rejoin the recording continuously).
"""

from __future__ import annotations

from envs.reaction.base import CrowdPath, CrowdStep, ReactiveCrowd, RecordedTracks, ReplayedCrowd
from envs.reaction.metrics import DisturbanceMetrics
from envs.reaction.params import MODEL_REVISIONS, REACTION_MODELS, ReactionParams, check_model, revision_rules

__all__ = [
    "MODEL_REVISIONS",
    "REACTION_MODELS",
    "CrowdPath",
    "CrowdStep",
    "DisturbanceMetrics",
    "ReactionParams",
    "ReactiveCrowd",
    "RecordedTracks",
    "ReplayedCrowd",
    "check_model",
    "make_reactive_crowd",
    "revision_rules",
]


def make_reactive_crowd(
    model: str, params: ReactionParams | None = None, *, robot_radius_m: float, pedestrian_radius_m: float
) -> ReactiveCrowd:
    """The crowd of reaction model ``model`` (one of :data:`REACTION_MODELS`).

    Args:
        model: ``none``, ``pause``, ``orca`` or ``social_force``.
        params: the constants (default :class:`ReactionParams`'s).
        robot_radius_m: the environment's robot radius, metres.
        pedestrian_radius_m: the environment's pedestrian radius, metres.

    Raises:
        ConfigError: an unknown model (listing the valid ones).
        ImportError: ``orca`` without ``pyrvo`` (saying how to install it).
    """
    check_model(model)
    params = ReactionParams() if params is None else params
    if model == "pause":
        from envs.reaction.pause import PausingCrowd as cls
    elif model == "orca":
        from envs.reaction.orca import OrcaCrowd as cls
    elif model == "social_force":
        from envs.reaction.social_force import SocialForceCrowd as cls
    else:
        cls = ReplayedCrowd
    return cls(params, robot_radius_m, pedestrian_radius_m)
