"""crowdnav-mesrnn: MESRNN trajectory prediction and robot navigation through replayed ETH/UCY crowds.

Importing the package registers the Gymnasium ids ``CrowdNav-MESRNN-v0``, ``CrowdNav-NoPred-v0``,
``CrowdNav-CV-v0`` and ``CrowdNav-Oracle-v0``.
"""

from __future__ import annotations

from typing import Any

from crowdnav_mesrnn._registration import register_envs
from crowdnav_mesrnn._version import __version__

register_envs()


def load_pretrained(model: str, split: str, **kwargs: Any) -> Any:
    """Load a shipped pretrained predictor (``"mesrnn"``, ``"srnn"`` or ``"vlstm"``) for a split.

    The predictor for split ``X`` was trained without scene ``X``.
    """
    from crowdnav_mesrnn.models.pretrained import load_pretrained as _load

    return _load(model, split, **kwargs)


__all__ = ["__version__", "load_pretrained", "register_envs"]
