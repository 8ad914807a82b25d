"""Training navigation policies (PPO or SAC) on ``CrowdNav-*`` from a YAML config; every run is a folder.

``python -m agents.train --config configs/agent/ppo.yaml --predictor mesrnn --split zara1 --seed 0
[--timesteps N] [--out RUN_DIR] [--resume] [--set key=value ...]`` (also ``crowdnav-mesrnn agent train``).

One module per concern, importing only downwards (``cli`` -> ``run`` -> ``callbacks`` and ``pretrain`` ->
``config``); ``config`` imports neither torch nor SB3, so a config is checked in a fraction of a second (``train`` is
imported from :mod:`agents.training.run` when first asked for):

- :mod:`agents.training.config`: the config file's layout (its ``pretrain:`` section too), loading it with
  overrides, the algorithm's arguments;
- :mod:`agents.training.pretrain`: the behaviour-cloning (and DAgger) warm start from a planner;
- :mod:`agents.training.logger`: ``progress.csv`` and TensorBoard;
- :mod:`agents.training.callbacks`: validation keeping the best model, checkpoints, the progress bar;
- :mod:`agents.training.run`: :func:`train`, the environments and the run folder;
- :mod:`agents.training.cli`: the command line.

Episodes are run by :mod:`agents.rollout`, run folders are read by :mod:`agents.runs`.
"""

from __future__ import annotations

from typing import Any

from agents.training.config import EvalConfig, PretrainConfig, TrainConfig, load_train_config

__all__ = ["EvalConfig", "PretrainConfig", "TrainConfig", "load_train_config", "train"]


def __getattr__(name: str) -> Any:
    if name == "train":  # SB3 and torch are imported with it, not with the package
        from agents.training.run import train

        return train
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
