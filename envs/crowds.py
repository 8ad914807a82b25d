"""Crowd sources, the replay and episode sampling, under their former common name.

They live in :mod:`envs.recordings` (building recordings: scripted, empty, synthetic), :mod:`envs.replay`
(continuous-time replay and perception) and :mod:`envs.episodes` (episode sampling); these names are
re-exported here so ``from envs.crowds import ...`` keeps working.
"""

from envs.episodes import Episode, EpisodeSampler, crowd_near_path, recording_extent
from envs.recordings import (
    EMPTY_NAME,
    SYNTHETIC_NAME,
    empty_recording,
    make_recording,
    scripted_recording,
    synthetic_recording,
)
from envs.replay import TIME_TOL_S, Perception, Replay, ReplayState

__all__ = [
    "EMPTY_NAME",
    "SYNTHETIC_NAME",
    "TIME_TOL_S",
    "Episode",
    "EpisodeSampler",
    "Perception",
    "Replay",
    "ReplayState",
    "crowd_near_path",
    "empty_recording",
    "make_recording",
    "recording_extent",
    "scripted_recording",
    "synthetic_recording",
]
