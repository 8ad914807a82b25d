"""Forecast sources: what the observation's ``forecasts`` hold, per pedestrian, at every environment time.

A source turns the replay at env time ``t`` into ``(n, H, 2)`` world positions at ``t + h * dt_s`` (h = 1..H) of
the perceived pedestrians, or None (no forecasts). This module holds the base class and the sources without a
predictor: none, the oracle (the replay's true future, :class:`TrueFuture`) and the noisy oracle. The predictor
sources are :class:`envs.forecasting.window.PredictorForecast` and
:class:`envs.forecasting.carried.CarriedPredictorForecast`; :func:`envs.forecasting.factory.make_forecast_source`
builds the one a configuration names.

Learned forecasts are out-of-sample: a recording is forecast by the predictor of the split holding it out
(:func:`split_of_recording`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from crowdnav_mesrnn.data.constants import SPLIT_TEST_RECORDINGS
from envs.replay import Replay


class ForecastModel(Protocol):
    """What the environment needs of a predictor (:class:`crowdnav_mesrnn.models.Predictor`)."""

    name: str
    obs_len: int
    pred_len: int

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray: ...


def split_of_recording(name: str) -> str | None:
    """The split whose held-out (test) recordings include ``name``; None for other crowds."""
    for split, names in SPLIT_TEST_RECORDINGS.items():
        if name in names:
            return split
    return None


@dataclass(frozen=True)
class TrueFuture:
    """The replay's future of some pedestrians on the environment's grid.

    Attributes:
        positions: ``(n, H, 2)`` metres at ``t + h * dt_s``; where the pedestrian has left the replay,
            its last position in the replay is held (so it can serve as an oracle forecast).
        valid: ``(n, H)`` bool: the pedestrian is in the replay at that time.
    """

    positions: np.ndarray
    valid: np.ndarray


def fill_forward(positions: np.ndarray, valid: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Hold the last valid position where ``valid`` is False.

    Args:
        positions: ``(n, H, 2)``; valid: ``(n, H)``; current: ``(n, 2)`` position at h = 0.
    """
    if valid.all():
        return positions.copy()
    h = positions.shape[1]
    idx = np.where(valid, np.arange(1, h + 1)[None, :], 0)
    idx = np.maximum.accumulate(idx, axis=1)
    full = np.concatenate([current[:, None, :], positions], axis=1)
    return np.take_along_axis(full, idx[..., None], axis=1)


class ForecastSource:
    """Base class: forecasts of some pedestrians of a replay at time ``t``.

    Attributes:
        name: the source's name (``"none"``, ``"cv"``, ``"mesrnn"``, ...).
        needs_truth: the source uses the replay's true future.
    """

    name: str = "base"
    needs_truth: bool = False
    active: bool = True
    memory: str | None = None
    """``window`` or ``carried`` for predictor sources, None for sources without memory."""

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        """``(len(rows), H, 2)`` world positions at ``t + h * dt_s`` of the pedestrians in ``rows`` (present at t)."""
        raise NotImplementedError


class NoForecast(ForecastSource):
    """No forecasts in the observation."""

    name = "none"
    active = False

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        return None


class OracleForecast(ForecastSource):
    """The replay's true future (held at the last position once a pedestrian has left)."""

    name = "oracle"
    needs_truth = True

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        assert truth is not None
        return truth.positions.copy()


class NoisyOracleForecast(ForecastSource):
    """The true future plus a drift error that grows linearly over the horizon.

    For each pedestrian and forecast time, ``z ~ N(0, sigma^2 I)`` (2-D) and the error at step h is
    ``(h / H) z``; ``sigma`` is set so the expected ADE is ``target_ade_m``:
    ``E|e_h| = (h / H) sigma sqrt(pi / 2)``, so ``ADE = sigma sqrt(pi / 2) (H + 1) / (2 H)``.
    Noise comes from the environment's generator (seeded by ``reset``); never cached.
    """

    name = "noisy_oracle"
    needs_truth = True

    def __init__(self, target_ade_m: float, horizon: int) -> None:
        self.target_ade_m = float(target_ade_m)
        self.horizon = horizon
        self.sigma = self.target_ade_m * 2 * horizon / ((horizon + 1) * math.sqrt(math.pi / 2))
        self.ramp = (np.arange(1, horizon + 1) / horizon)[None, :, None]

    def forecast(
        self, replay: Replay, t_s: float, rows: np.ndarray, truth: TrueFuture | None, rng: np.random.Generator
    ) -> np.ndarray | None:
        assert truth is not None
        z = rng.normal(0.0, self.sigma, size=(len(rows), 1, 2))
        return truth.positions + self.ramp * z
