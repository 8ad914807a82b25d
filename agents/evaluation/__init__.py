"""Evaluate a policy — a training run, an SB3 model, or a planner — on a fixed, seeded list of episodes.

``python -m agents.evaluate RUN_DIR_OR_PLANNER --predictor mesrnn --split zara1 --episodes 500 --json``
(also ``crowdnav-mesrnn agent evaluate ...``) replays the split's held-out scene (``part="test"``) over
:func:`agents.rollout.evaluation_seeds` — the same list for every arm and policy, so comparisons are paired — with
deterministic actions, and by default only episodes in which a pedestrian comes within sensor range
of the straight path (``require_pedestrians``). Per-episode metrics go to ``episodes.csv`` and the summary
to ``summary.json``, in ``--out`` or else a new ``runs/eval/<policy>_<predictor>_<split>_s<seed>_<UTC time>/``
(:func:`default_eval_dir`); the summary gives outcome rates with 95 % Wilson intervals and metric means with
bootstrap intervals (:mod:`agents.stats`).

One module per concern: :mod:`agents.evaluation.run` (:func:`evaluate`), :mod:`agents.evaluation.summary` (the
aggregates, the ceiling fraction, ``episodes.csv``) and :mod:`agents.evaluation.cli` (the command line). Episodes
are run by :func:`agents.rollout.run_episodes`, policies loaded by :func:`agents.runs.load_policy`.
"""

from __future__ import annotations

from agents.evaluation.run import default_eval_dir, evaluate, evaluation_env_kwargs
from agents.evaluation.summary import (
    OUTCOMES,
    SUCCESS_ONLY_METRICS,
    ceiling_fraction,
    episodes_csv,
    format_summary,
    read_episodes,
    summarise,
)

__all__ = [
    "OUTCOMES",
    "SUCCESS_ONLY_METRICS",
    "ceiling_fraction",
    "default_eval_dir",
    "episodes_csv",
    "evaluate",
    "evaluation_env_kwargs",
    "format_summary",
    "read_episodes",
    "summarise",
]
