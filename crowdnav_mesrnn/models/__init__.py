"""Trajectory predictors: the structural RNN family (MESRNN, SRNN, VLSTM) and constant velocity."""

from typing import Any

from crowdnav_mesrnn.models import base as _base
from crowdnav_mesrnn.models.base import ConstantVelocity, Predictor

__all__ = ["LEARNED_MODELS", "MODELS", "ConstantVelocity", "Predictor", "get_predictor"]


def get_predictor(name: str, split: str | None = None) -> Predictor:
    """A ready predictor by name: :func:`crowdnav_mesrnn.predictors.load` (``"cv"``, a pretrained
    ``"mesrnn"``/``"srnn"``/``"vlstm"`` for ``split``, an installed plug-in's name or an import path
    ``package.module:Factory``); its :class:`~crowdnav_mesrnn.predictors.PluginError` (a ValueError) names the valid
    ones."""
    from crowdnav_mesrnn import predictors

    return predictors.load(name, split)


def __getattr__(name: str) -> Any:
    """``LEARNED_MODELS`` and ``MODELS``, deprecated (see :mod:`crowdnav_mesrnn.models.base`)."""
    return getattr(_base, name)
