"""Deprecated import path of :mod:`agents.training` (kept for one release; importing it warns).

``python -m agents.train`` remains the training command (:func:`agents.training.cli.main`, without a warning).
Models saved with a ``lin_<x>`` schedule pickle ``agents.train.LinearSchedule``; this module resolves it.
"""

from __future__ import annotations

import sys
import warnings

if __name__ == "__main__":  # the command, not a deprecated import: arguments checked before torch is imported
    from agents.training.cli import main as _main

    sys.exit(_main())

from agents.actions import action_set
from agents.runs import PROJECT_KEY
from agents.training.callbacks import Checkpoint, Progress, Validation, latest_checkpoint, save_checkpoint
from agents.training.cli import add_train_arguments, config_from_args, main, run_from_args
from agents.training.config import (
    ALGOS,
    DEFAULT_CONFIG,
    ENV_ID_OF,
    PROJECT_KEYS,
    RUN_ENV_KEYS,
    UNSUPPORTED_ZOO_KEYS,
    VEC_ENVS,
    ZOO_KEYS,
    EvalConfig,
    LinearSchedule,
    TrainConfig,
    algorithm_kwargs,
    env_id_for,
    load_train_config,
    policy_class,
)
from agents.training.logger import ProgressCSV, make_logger
from agents.training.run import (
    default_run_dir,
    make_env,
    make_vec_env,
    predictor_weights,
    prepare_training_forecasts,
    resolved_yaml,
    rollout_steps,
    steps_trained,
    train,
)

__all__ = [
    "ALGOS",
    "DEFAULT_CONFIG",
    "ENV_ID_OF",
    "PROJECT_KEY",
    "PROJECT_KEYS",
    "RUN_ENV_KEYS",
    "UNSUPPORTED_ZOO_KEYS",
    "VEC_ENVS",
    "ZOO_KEYS",
    "Checkpoint",
    "EvalConfig",
    "LinearSchedule",
    "Progress",
    "ProgressCSV",
    "TrainConfig",
    "Validation",
    "action_set",
    "add_train_arguments",
    "algorithm_kwargs",
    "config_from_args",
    "default_run_dir",
    "env_id_for",
    "latest_checkpoint",
    "load_train_config",
    "main",
    "make_env",
    "make_logger",
    "make_vec_env",
    "policy_class",
    "predictor_weights",
    "prepare_training_forecasts",
    "resolved_yaml",
    "rollout_steps",
    "run_from_args",
    "save_checkpoint",
    "steps_trained",
    "train",
]

warnings.warn(
    "agents.train is deprecated and will be removed in the next release: import from agents.training "
    "(python -m agents.train stays the command)",
    DeprecationWarning,
    stacklevel=2,
)
