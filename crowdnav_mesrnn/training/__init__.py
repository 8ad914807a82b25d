"""Training of the structural RNN predictors.

- :mod:`~crowdnav_mesrnn.training.trainer`: configs, losses and the resumable :class:`~crowdnav_mesrnn.training.trainer.Trainer`
  (``crowdnav-mesrnn predictor train``).
- :mod:`~crowdnav_mesrnn.training.head_fit`: the distribution head fitted on frozen point weights
  (``crowdnav-mesrnn predictor fit-head``).

The names this package held as a single module are still served from it, with a ``DeprecationWarning``.
"""

from __future__ import annotations

from crowdnav_mesrnn._deprecated import moved_attributes

__getattr__ = moved_attributes(
    __name__,
    dict.fromkeys(
        (
            "CONFIG_DIR",
            "PRECISIONS",
            "SELECT_ON",
            "TrainConfig",
            "Trainer",
            "TrainingDivergedError",
            "clip_gradients",
            "gaussian_nll_loss",
            "keep_freed_memory",
            "load_configs",
            "make_optimizer",
            "masked_loss",
            "rotate_windows",
            "training_loss",
        ),
        "crowdnav_mesrnn.training.trainer",
    ),
)
