"""Forecast uncertainty for the observation: per forecast step, the radius of a disc holding the true position
with a calibrated probability (``forecast_uncertainty=True``, level ``forecast_uncertainty_level``).

Every arm with forecasts gets the same ``(K, H)`` key; what the radius means depends on the forecast source:

- ``cv`` and the learned predictors: the conformal calibration of :mod:`crowdnav_mesrnn.uncertainty.calibration` (an error
  model fitted on the split's training windows, thresholds per forecast step on its validation windows; the
  split is the one whose predictor forecasts the recording, so no scene's own data enter its radii). A
  pedestrian's radius grows with its last observed displacement and with the horizon. Calibrations are
  computed once per (predictor weights, split, data) and kept as JSON files beside the forecast cache.
- ``oracle``: 0 (the true future).
- ``noisy_oracle``: exact, from the noise it adds (``(h / H) z``, ``z ~ N(0, σ² I)``): ``(h / H) σ sqrt(χ²₂(c))``.

The radii are on the predictor's annotation grid (0 at the annotation itself) and are resampled onto
``t + h * dt_s`` with the forecasts' linear interpolation (:func:`envs.forecasting.resampling.resample_matrix`).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.utils import atomic_write_json, file_lock
from envs.config import CrowdNavConfig
from envs.forecasting.cache import cache_root, predictor_fingerprint, recording_fingerprint
from envs.forecasting.resampling import resample_matrix, time_key
from envs.forecasting.sources import NoisyOracleForecast, split_of_recording
from envs.replay import Replay


class UncertaintySource:
    """Radii ``(m, H)`` metres for the perceived pedestrians ``rows`` of a replay at ``t_s``."""

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        raise NotImplementedError


class ZeroUncertainty(UncertaintySource):
    """The oracle: its forecast is the truth."""

    def __init__(self, horizon: int) -> None:
        self.horizon = horizon

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        return np.zeros((len(rows), self.horizon))


class NoisyOracleUncertainty(UncertaintySource):
    """The noisy oracle's own noise: radius ``(h / H) σ sqrt(−2 ln(1 − c))`` at env step ``h``."""

    def __init__(self, source: NoisyOracleForecast, level: float) -> None:
        self.per_step = source.ramp[0, :, 0] * source.sigma * math.sqrt(-2.0 * math.log1p(-level))

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        return np.broadcast_to(self.per_step, (len(rows), len(self.per_step))).copy()


class CalibratedUncertainty(UncertaintySource):
    """Conformal radii of a point predictor (``cv`` or shipped point weights) per recording's split.

    Args:
        name: ``cv``, ``mesrnn``, ``srnn`` or ``vlstm``.
        default_split: split for recordings outside every split's test part (synthetic crowds).
        level: coverage level of the regions.
        dt_s: the environment's step, seconds.
        horizon: H, the environment's forecast steps.
        cache_dir: folder of the calibration files (None: memory only).
        data_dir: ETH/UCY folder (default: the usual search).
    """

    def __init__(
        self,
        name: str,
        default_split: str,
        level: float,
        dt_s: float,
        horizon: int,
        cache_dir: Path | None,
        data_dir: str | None = None,
    ) -> None:
        self.name = name
        self.default_split = default_split
        self.level = level
        self.dt_s = dt_s
        self.horizon = horizon
        self.cache_dir = cache_dir
        self.data_dir = data_dir
        self._calibrations: dict[str, Any] = {}
        self._weights: dict[tuple[float, int], np.ndarray] = {}

    def calibration(self, split: str) -> Any:
        """The split's :class:`crowdnav_mesrnn.uncertainty.calibration.Calibration` (from the cache file, else fitted and saved)."""
        if split not in self._calibrations:
            self._calibrations[split] = load_or_fit_calibration(
                self.name, split, self.level, self.cache_dir, self.data_dir
            )
        return self._calibrations[split]

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        cal = self.calibration(split_of_recording(replay.name) or self.default_split)
        speed = np.zeros(len(rows))
        if index >= 1:
            both = replay.present[index, rows] & replay.present[index - 1, rows]
            disp = replay.positions[index, rows] - replay.positions[index - 1, rows]
            speed = np.where(both, np.hypot(disp[:, 0], disp[:, 1]), 0.0)
        per_step = cal.radius_m(self.level, speed)  # (m, P) on the annotation grid
        key = (replay.step_s, time_key(age_s))
        weights = self._weights.get(key)
        if weights is None:
            weights = self._weights[key] = resample_matrix(
                replay.step_s, self.dt_s, self.horizon, per_step.shape[1], age_s
            )
        return per_step @ weights[:, 1:].T  # radius 0 at the annotation itself


def calibration_key(name: str, split: str, levels: tuple[float, ...], data_dir: str | None) -> str:
    """Digest of what a calibration depends on: the predictor's weights, the split's training and validation
    recordings, the levels and the calibration format."""
    from crowdnav_mesrnn.data.recordings import load_split
    from crowdnav_mesrnn.uncertainty.conformal import CALIBRATION_FORMAT

    h = hashlib.sha256()
    if predictors.kind(name) == predictors.BASELINE:  # no weights: the name is the predictor
        h.update(name.encode())
    else:
        h.update(str(predictor_fingerprint(predictors.load(name, split))).encode())
    for part in ("train", "val"):
        for rec in load_split(split, part, data_dir):
            h.update(f"{part}:{rec.name}:{recording_fingerprint(rec)}".encode())
    h.update(json.dumps({"levels": list(levels), "format": CALIBRATION_FORMAT, "score": "scaled"}).encode())
    return h.hexdigest()[:20]


def load_or_fit_calibration(
    name: str, split: str, level: float, cache_dir: Path | None, data_dir: str | None = None
) -> Any:
    """The ``scaled`` calibration of predictor ``name`` (point head) on ``split`` at :data:`LEVELS` and ``level``:
    read from ``cache_dir/calibration/`` when a file with the same key exists, else fitted (on the training and
    validation windows of the split) and written atomically under a lock, so concurrent processes fit it once."""
    from crowdnav_mesrnn.uncertainty.calibration import LEVELS, Calibration, fit_calibration, forecaster_for

    levels = tuple(sorted({*LEVELS, float(level)}))

    def fit() -> Calibration:
        return fit_calibration(forecaster_for(name, split), split, "scaled", levels, data_dir)

    if cache_dir is None:
        return fit()
    path = cache_dir / "calibration" / f"{name}_{split}_{calibration_key(name, split, levels, data_dir)}.json"

    def read() -> Calibration | None:
        if not path.is_file():
            return None
        try:
            return Calibration.from_dict(json.loads(path.read_text()))
        except (ValueError, KeyError, TypeError):  # unreadable or another format: refit and overwrite
            return None

    held = read()
    if held is not None:
        return held
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with file_lock(path.with_name(path.name + ".lock")):
            held = read()
            if held is None:
                held = fit()
                atomic_write_json(path, held.to_dict())
    except OSError:  # an unwritable folder: keep it in memory
        held = held or fit()
    return held


def make_uncertainty_source(config: CrowdNavConfig, forecaster: Any, predictor: Any = None) -> UncertaintySource:
    """The uncertainty of the forecast source ``forecaster`` that ``config`` (or the predictor object
    ``predictor``) built: by the kind of ``config.predictor`` (:func:`crowdnav_mesrnn.predictors.kind`), zero for
    the oracle, the noisy oracle's own noise, or calibrated radii (level ``forecast_uncertainty_level``) for the
    shipped point predictors, the calibrations kept beside the forecast cache (``forecast_disk_cache``).

    Raises:
        ConfigError: a predictor object, a plug-in or ``none`` (no calibration), or ``carried`` forecasts.
    """
    level, dt_s, horizon = config.forecast_uncertainty_level, config.dt_s, config.horizon_steps
    calibrated = (predictors.BASELINE, predictors.PRETRAINED)
    if predictor is not None:
        named = predictors.names(*calibrated, predictors.TRUTH, predictors.NOISY_TRUTH, plugins=False)
        raise ConfigError(
            f"forecast_uncertainty needs a named forecast source ({', '.join(named)}); "
            f"a predictor object ({getattr(forecaster, 'name', None)!r}) has no calibration"
        )
    name = config.predictor
    kind = predictors.kind(name)
    if kind == predictors.TRUTH:
        return ZeroUncertainty(horizon)
    if kind == predictors.NOISY_TRUTH:
        assert isinstance(forecaster, NoisyOracleForecast)
        return NoisyOracleUncertainty(forecaster, level)
    if kind in calibrated:
        if getattr(forecaster, "memory", None) == "carried":
            raise ConfigError(
                "forecast_uncertainty is calibrated for window forecasts (forecast_memory 'window'), not 'carried'"
            )
        cache_dir = cache_root(config.forecast_cache_dir) if config.forecast_disk_cache else None
        return CalibratedUncertainty(name, config.split, level, dt_s, horizon, cache_dir, config.data_dir)
    raise ConfigError(f"forecast_uncertainty has nothing to measure for predictor {name!r} (no forecasts)")
