"""Training navigation policies (PPO or SAC) on ``CrowdNav-*`` from a YAML config; every run is a folder.

``python -m agents.train --config configs/agent/ppo.yaml --predictor mesrnn --split zara1 --seed 0
[--timesteps N] [--out RUN_DIR] [--resume] [--set key=value ...]`` (also ``crowdnav-mesrnn agent train``).

One module per concern, importing only downwards (``cli`` -> ``run`` -> ``callbacks`` -> ``config`` ->
``pretrain``):

- :mod:`agents.training.config`: the config file's layout, loading it with overrides, the algorithm's arguments;
- :mod:`agents.training.pretrain`: the behaviour-cloning (and DAgger) warm start from a planner;
- :mod:`agents.training.logger`: ``progress.csv`` and TensorBoard;
- :mod:`agents.training.callbacks`: validation keeping the best model, checkpoints, the progress bar;
- :mod:`agents.training.run`: :func:`train`, the environments and the run folder;
- :mod:`agents.training.cli`: the command line.

Episodes are run by :mod:`agents.rollout`, run folders are read by :mod:`agents.runs`.
"""

from __future__ import annotations

from agents.training.config import EvalConfig, TrainConfig, load_train_config
from agents.training.pretrain import PretrainConfig
from agents.training.run import train

__all__ = ["EvalConfig", "PretrainConfig", "TrainConfig", "load_train_config", "train"]
