"""The predictor interface shared by evaluation and the environment."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN

#: Deprecated name lists, answered by the registry (:func:`crowdnav_mesrnn.predictors.names`) when read.
_DEPRECATED_LISTS = {"LEARNED_MODELS": ("PRETRAINED",), "MODELS": ("BASELINE", "PRETRAINED")}


def __getattr__(name: str) -> tuple[str, ...]:
    """``LEARNED_MODELS`` and ``MODELS``, deprecated: ask :func:`crowdnav_mesrnn.predictors.names`. The registry
    imports this module, so it is looked up by name here (a deprecated alias is not an import edge)."""
    if name not in _DEPRECATED_LISTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib
    import warnings

    warnings.warn(
        f"crowdnav_mesrnn.models.{name} is deprecated; use crowdnav_mesrnn.predictors.names(...)",
        DeprecationWarning,
        stacklevel=2,
    )
    registry = importlib.import_module("crowdnav_mesrnn.predictors")
    kinds = [getattr(registry, k) for k in _DEPRECATED_LISTS[name]]
    return registry.names(*kinds, plugins=False)


@runtime_checkable
class Predictor(Protocol):
    """Forecasts every pedestrian present at the last observed step.

    Steps are annotation steps of the recording the histories come from (0.4 s, or 0.667 s for
    ``biwi_eth``); positions are metres in the world frame.
    """

    name: str
    obs_len: int
    pred_len: int

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Forecast future positions.

        Args:
            history: ``(obs_len, N, 2)`` observed positions, metres (values where ``mask`` is False
                are ignored).
            mask: ``(obs_len, N)`` bool presence.

        Returns:
            ``(N, pred_len, 2)`` float32 metres. Rows of pedestrians absent at the last observed step
            hold their last observed position, or 0 if never observed; they carry no forecast.
        """
        ...


def check_history(history: np.ndarray, mask: np.ndarray, obs_len: int = OBS_LEN) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert a history; raises ``ValueError`` naming the bad shape or value."""
    history = np.asarray(history, dtype=np.float32)
    mask = np.asarray(mask, dtype=bool)
    if history.ndim != 3 or history.shape[-1] != 2 or history.shape[0] != obs_len:
        raise ValueError(f"history must have shape ({obs_len}, N, 2), got {history.shape}")
    if mask.shape != history.shape[:2]:
        raise ValueError(f"mask must have shape {history.shape[:2]}, got {mask.shape}")
    if not np.all(np.isfinite(history[mask])):
        raise ValueError("history holds NaN or infinite positions where mask is True")
    return np.where(mask[..., None], history, 0.0).astype(np.float32), mask


def last_known(history: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(N, 2)`` each pedestrian's last observed position (0 if never observed)."""
    t_idx = np.where(mask, np.arange(mask.shape[0])[:, None], -1).max(axis=0)
    out = history[np.clip(t_idx, 0, None), np.arange(mask.shape[1])]
    return np.where((t_idx >= 0)[:, None], out, 0.0).astype(np.float32)


class ConstantVelocity:
    """Extrapolates the last observed velocity ``p(t) − p(t−1)`` (0 when ``t−1`` is unobserved)."""

    name = "cv"

    def __init__(self, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN) -> None:
        self.obs_len = obs_len
        self.pred_len = pred_len

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        history, mask = check_history(history, mask, self.obs_len)
        last = last_known(history, mask)
        both = mask[-1] & mask[-2]
        vel = np.where(both[:, None], history[-1] - history[-2], 0.0)
        k = np.arange(1, self.pred_len + 1, dtype=np.float32)[None, :, None]
        out = last[:, None, :] + k * vel[:, None, :]
        out[~mask[-1]] = last[~mask[-1], None, :]
        return out.astype(np.float32)
