"""Evaluate a policy — a training run, an SB3 model, or a planner — on a fixed, seeded list of episodes.

``python -m agents.evaluate RUN_DIR_OR_PLANNER --predictor mesrnn --split zara1 --episodes 500 --json``
(also ``crowdnav-mesrnn agent evaluate ...``) replays the split's held-out scene (``part="test"``) over
:func:`agents.rollout.evaluation_seeds` — the same list for every arm and policy, so comparisons are paired — with
deterministic actions, and by default only episodes in which a pedestrian comes within sensor range
of the straight path (``require_pedestrians``). Per-episode metrics go to ``episodes.csv`` and the summary
to ``summary.json``, in ``--out`` or else a new ``runs/eval/<policy>_<predictor>_<split>_s<seed>_<UTC time>/``
(:func:`default_eval_dir`); the summary gives outcome rates with 95 % Wilson intervals and metric means with
bootstrap intervals (:mod:`agents.stats`). ``--episodes-from val`` replays the training scenes' validation period
instead (:data:`EPISODE_SOURCES`): the episodes choices are made on.

One module per concern: :mod:`agents.evaluation.run` (:func:`evaluate`), :mod:`agents.evaluation.summary` (the
aggregates, the ceiling fraction, ``episodes.csv``) and :mod:`agents.evaluation.cli` (the command line). Episodes
are run by :func:`agents.rollout.run_episodes`, policies loaded by :func:`agents.runs.load_policy`.
"""

from __future__ import annotations

from typing import Any, Final

#: Which episodes an evaluation replays (``episodes_from``) -> the environment's ``part`` and ``episode_time``:
#: ``test``, the split's held-out scene over its whole duration (what results report); ``val``, the split's training
#: scenes in their validation period (the last ``val_fraction`` of each recording, where training selects its best
#: model) -- the episodes every choice (recipe, planner settings, teacher) is made on, never a held-out result.
EPISODE_SOURCES: Final[dict[str, tuple[str, str]]] = {"test": ("test", "all"), "val": ("train", "val")}


def episode_part(episodes_from: str) -> dict[str, str]:
    """The environment settings ``{"part", "episode_time"}`` of :data:`EPISODE_SOURCES`' entry ``episodes_from``.

    Raises:
        ValueError: an unknown value, naming it and the allowed ones.
    """
    if episodes_from not in EPISODE_SOURCES:
        raise ValueError(f"episodes_from must be one of {', '.join(EPISODE_SOURCES)}, got {episodes_from!r}")
    part, episode_time = EPISODE_SOURCES[episodes_from]
    return {"part": part, "episode_time": episode_time}


#: Where each public name lives; imported when first asked for, so that the command line's parsers (``agent
#: evaluate``) load neither scipy nor the environment.
_HOMES: dict[str, str] = {
    "default_eval_dir": "agents.evaluation.run",
    "evaluate": "agents.evaluation.run",
    "evaluation_env_kwargs": "agents.evaluation.run",
    "OUTCOMES": "agents.evaluation.summary",
    "SUCCESS_ONLY_METRICS": "agents.evaluation.summary",
    "ceiling_fraction": "agents.evaluation.summary",
    "episodes_csv": "agents.evaluation.summary",
    "format_summary": "agents.evaluation.summary",
    "read_episodes": "agents.evaluation.summary",
    "summarise": "agents.evaluation.summary",
}

__all__ = [
    "EPISODE_SOURCES",
    "OUTCOMES",
    "SUCCESS_ONLY_METRICS",
    "ceiling_fraction",
    "default_eval_dir",
    "episode_part",
    "episodes_csv",
    "evaluate",
    "evaluation_env_kwargs",
    "format_summary",
    "read_episodes",
    "summarise",
]


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        import importlib

        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
