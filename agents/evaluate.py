"""Deprecated import path of :mod:`agents.evaluation`, :mod:`agents.rollout` and :mod:`agents.runs` (kept for one
release; importing it warns).

``python -m agents.evaluate`` remains the evaluation command (:func:`agents.evaluation.cli.main`, without a
warning).
"""

from __future__ import annotations

import sys
import warnings

if __name__ == "__main__":  # the command, not a deprecated import: arguments checked before torch is imported
    from agents.evaluation.cli import main as _main

    sys.exit(_main())

from agents.entry import parse_set
from agents.evaluation.cli import add_evaluate_arguments, main, run_from_args
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
from agents.rollout import (
    EPISODE_COLUMNS,
    METRICS,
    SB3Policy,
    StepHook,
    episode_row,
    evaluation_seeds,
    prepare_forecasts,
    run_episodes,
)
from agents.runs import (
    RUN_MODELS,
    algo_of_model,
    check_spaces,
    config_of,
    export_policy,
    load_policy,
    load_sb3,
    model_path,
    run_settings,
    without_optimizer_state,
)

__all__ = [
    "EPISODE_COLUMNS",
    "METRICS",
    "OUTCOMES",
    "RUN_MODELS",
    "SUCCESS_ONLY_METRICS",
    "SB3Policy",
    "StepHook",
    "add_evaluate_arguments",
    "algo_of_model",
    "ceiling_fraction",
    "check_spaces",
    "config_of",
    "default_eval_dir",
    "episode_row",
    "episodes_csv",
    "evaluate",
    "evaluation_env_kwargs",
    "evaluation_seeds",
    "export_policy",
    "format_summary",
    "load_policy",
    "load_sb3",
    "main",
    "model_path",
    "parse_set",
    "prepare_forecasts",
    "read_episodes",
    "run_episodes",
    "run_from_args",
    "run_settings",
    "summarise",
    "without_optimizer_state",
]

warnings.warn(
    "agents.evaluate is deprecated and will be removed in the next release: import from agents.evaluation, "
    "agents.rollout or agents.runs (python -m agents.evaluate stays the command)",
    DeprecationWarning,
    stacklevel=2,
)
