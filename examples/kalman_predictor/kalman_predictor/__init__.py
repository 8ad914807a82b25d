"""A constant-velocity Kalman filter behind crowdnav-mesrnn's predictor protocol.

State per pedestrian: position and velocity ``[x, y, vx, vy]`` (metres, metres per annotation step). The
motion model is constant velocity with white-noise acceleration (variance ``accel_var`` in (m/step²)²); the
measurement is the annotated position with noise variance ``meas_var`` (m²). The filter runs over the
observed steps of each pedestrian (predicting through steps where it is not annotated), then predicts
``pred_len`` steps ahead; the forecast is the predicted mean, and :meth:`KalmanPredictor.forecast_distribution`
also returns the predicted position covariance.
"""

from __future__ import annotations

import hashlib

import numpy as np

__version__ = "0.1.0"

_F = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
_H = np.array([[1, 0, 0, 0], [0, 1, 0, 0]], dtype=np.float64)
_G = np.array([[0.5, 0], [0, 0.5], [1, 0], [0, 1]], dtype=np.float64)  # acceleration -> state over one step


class KalmanPredictor:
    """Constant-velocity Kalman filter for every pedestrian at once (vectorised over N).

    Args:
        split: the leave-one-out split whose held-out scene will be forecast. The filter has no trained
            weights, so it is ignored (a learned plug-in would load weights trained without that scene).
        accel_var: white-noise acceleration variance, (m/step²)².
        meas_var: position measurement variance, m².
        init_speed_var: variance of the unknown initial velocity, (m/step)².
        obs_len: observed annotation steps.
        pred_len: predicted annotation steps.
    """

    name = "kalman"

    def __init__(
        self,
        split: str | None = None,
        accel_var: float = 0.01,
        meas_var: float = 0.01,
        init_speed_var: float = 1.0,
        obs_len: int = 8,
        pred_len: int = 12,
    ) -> None:
        for key, value in (("accel_var", accel_var), ("meas_var", meas_var), ("init_speed_var", init_speed_var)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{key} must be a finite number > 0, got {value!r}")
        self.split = split
        self.accel_var = float(accel_var)
        self.meas_var = float(meas_var)
        self.init_speed_var = float(init_speed_var)
        self.obs_len = int(obs_len)
        self.pred_len = int(pred_len)
        self._q = self.accel_var * _G @ _G.T
        self._r = self.meas_var * np.eye(2)

    def cache_fingerprint(self) -> str:
        """A digest of the parameters: the forecast cache keys this plug-in's forecasts on it."""
        params = (__version__, self.accel_var, self.meas_var, self.init_speed_var, self.obs_len, self.pred_len)
        return hashlib.sha256(repr(params).encode()).hexdigest()

    def _filter(self, history: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filtered state ``(N, 4)`` and covariance ``(N, 4, 4)`` at the last observed step."""
        history = np.asarray(history, dtype=np.float64)
        mask = np.asarray(mask, dtype=bool)
        if history.shape != (self.obs_len, mask.shape[1], 2) or mask.shape[0] != self.obs_len:
            raise ValueError(
                f"history must be ({self.obs_len}, N, 2) with mask ({self.obs_len}, N); "
                f"got {history.shape} and {mask.shape}"
            )
        n = history.shape[1]
        x = np.zeros((n, 4))
        p = np.tile(np.diag([self.meas_var, self.meas_var, self.init_speed_var, self.init_speed_var]), (n, 1, 1))
        started = np.zeros(n, dtype=bool)
        for t in range(self.obs_len):
            # predict everyone already started
            x[started] = x[started] @ _F.T
            p[started] = _F @ p[started] @ _F.T + self._q
            seen = mask[t]
            new = seen & ~started
            x[new, :2] = history[t, new]
            upd = seen & started
            if upd.any():
                s = _H @ p[upd] @ _H.T + self._r  # (k, 2, 2)
                k = p[upd] @ _H.T @ np.linalg.inv(s)  # (k, 4, 2)
                innov = history[t, upd] - x[upd] @ _H.T  # (k, 2)
                x[upd] = x[upd] + np.einsum("kij,kj->ki", k, innov)
                p[upd] = (np.eye(4) - k @ _H) @ p[upd]
            started |= seen
        return x, p

    def forecast_distribution(self, history: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(obs_len, N, 2)`` metres + ``(obs_len, N)`` bool -> mean ``(N, pred_len, 2)`` metres and covariance
        ``(N, pred_len, 2, 2)`` m² of each future position. Pedestrians absent at the last observed step hold
        their last state's position (no forecast is read for them)."""
        x, p = self._filter(history, mask)
        n = x.shape[0]
        mean = np.zeros((n, self.pred_len, 2))
        cov = np.zeros((n, self.pred_len, 2, 2))
        last = np.asarray(mask, dtype=bool)[-1]
        for j in range(self.pred_len):
            x = x @ _F.T
            p = _F @ p @ _F.T + self._q
            mean[:, j] = x[:, :2]
            cov[:, j] = _H @ p @ _H.T
        gone = ~last
        if gone.any():  # by the protocol's convention: the last observed position (these rows are not read)
            m = np.asarray(mask, dtype=bool)
            t_last = np.where(m, np.arange(m.shape[0])[:, None], 0).max(axis=0)
            held = np.asarray(history, dtype=np.float64)[t_last, np.arange(n)]
            mean[gone] = held[gone, None, :]
        return mean.astype(np.float32), cov.astype(np.float32)

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``(obs_len, N, 2)`` metres + ``(obs_len, N)`` bool -> ``(N, pred_len, 2)`` float32 metres (the mean)."""
        return self.forecast_distribution(history, mask)[0]
