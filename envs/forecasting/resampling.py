"""From the predictor's annotation grid to the environment's time grid.

A predictor forecasts at the annotation steps ``tau + j * step_s`` (j = 1..P) after the annotation it was given
(``step_s``: 0.4 s, or 0.667 s for ``biwi_eth``); the observation wants positions at ``t + h * dt_s``
(h = 1..H). Values are interpolated linearly in time between annotation steps and held at the last one beyond
the forecast. The same weights resample forecasts (:mod:`envs.forecasting.window`) and uncertainty radii
(:mod:`envs.forecasting.uncertainty`).
"""

from __future__ import annotations

import numpy as np


def time_key(t_s: float) -> int:
    """Cache key of a time: tenths of milliseconds (env times are multiples of dt_s, not exact floats)."""
    return round(t_s * 1e4)


def resample_matrix(step_s: float, dt_s: float, horizon: int, pred_len: int, offset_s: float = 0.0) -> np.ndarray:
    """:func:`resample_weights` as a ``(H, pred_len + 1)`` matrix: row ``h`` weighs the values at ``j = 0..pred_len``."""
    j0, j1, w = resample_weights(step_s, dt_s, horizon, pred_len, offset_s)
    matrix = np.zeros((horizon, pred_len + 1))
    rows = np.arange(horizon)
    np.add.at(matrix, (rows, j0), 1.0 - w)
    np.add.at(matrix, (rows, j1), w)
    return matrix


def resample_weights(
    step_s: float, dt_s: float, horizon: int, pred_len: int, offset_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation from the annotation grid ``j * step_s`` (j = 0..pred_len) onto ``offset_s + h * dt_s``
    (h = 1..H); ``offset_s`` >= 0 is how far the wanted grid's origin lies after the annotation grid's.

    Returns:
        ``(j0, j1, w)`` each ``(H,)``: value = (1 - w) * f[j0] + w * f[j1] (held at j = pred_len beyond).
    """
    u = (offset_s + np.arange(1, horizon + 1) * dt_s) / step_s
    u = np.minimum(u, pred_len)
    j0 = np.floor(u + 1e-9).astype(np.int64)
    j0 = np.minimum(j0, pred_len)
    w = u - j0
    w = np.where(np.abs(w) < 1e-9, 0.0, w)
    j1 = np.minimum(j0 + 1, pred_len)
    return j0, j1, w
