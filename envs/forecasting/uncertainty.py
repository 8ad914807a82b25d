"""Forecast uncertainty for the observation: per forecast step, the radius of a disc holding the true position
with a calibrated probability (``forecast_uncertainty=True``, level ``forecast_uncertainty_level``).

Every arm with forecasts gets the same ``(K, H)`` key; what the radius means depends on the forecast source:

- ``cv``, ``cv_gaussian`` and the learned predictors: the conformal calibration of
  :mod:`crowdnav_mesrnn.uncertainty.calibration` (``scaled`` score: thresholds per forecast step on the split's
  validation windows, applied to a Gaussian around each forecast: for a point forecast an error model fitted on the
  split's training windows, whose scale grows with the pedestrian's last observed displacement and with the horizon;
  for ``cv_gaussian`` its own Gaussian, the same for every pedestrian). The split is the one whose predictor
  forecasts the recording, so no scene's own data enter its radii. Calibrations are computed once per (predictor
  weights, split, data) and kept as JSON files beside the forecast cache. A radius is the threshold times the
  Gaussian's major semi-axis (:meth:`~crowdnav_mesrnn.uncertainty.conformal.Calibration.unit_m`).
- ``oracle``: 0 (the true future).
- ``noisy_oracle``: exact, from the noise it adds (``(h / H) z``, ``z ~ N(0, σ² I)``): ``(h / H) σ sqrt(χ²₂(c))``.

**Which thresholds** (``forecast_uncertainty_method``, calibrated sources only). ``split`` (the default): the split
conformal thresholds, fixed. ``online``: the strictly causal ``"observed"`` rule with step-size experts of
:mod:`crowdnav_mesrnn.uncertainty.online_conformal` (:class:`~crowdnav_mesrnn.uncertainty.online_conformal.ExpertTracker`),
run inside each episode (:class:`OnlineUncertainty`). Every annotation of the episode is a forecast time: the tracker
starts from the split thresholds at the episode's first annotation, and at each later annotation ``k`` it first scores
the forecasts made at the episode's annotations ``k − h`` (``h`` = 1..12, step ``h`` of each) against the positions
annotated at ``k``, over the pedestrians present in every frame from the forecast's first observed one through ``k``
(the rule's rows: every pedestrian of the scene, as the forecast source sees them, not only the ``K`` the robot
observes), then gives the thresholds used at ``k``. Nothing annotated after ``k`` enters. It restarts every episode:
episodes are independent draws, and an episode's radii then depend on that episode alone (as every other key of the
observation does), so they are the same whichever episodes ran before in the process.

The radii are on the predictor's annotation grid (0 at the annotation itself) and are resampled onto
``t + h * dt_s`` with the forecasts' linear interpolation (:func:`envs.forecasting.resampling.resample_matrix`).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import OBS_LEN
from crowdnav_mesrnn.utils import atomic_write_json, file_lock
from envs.config import CrowdNavConfig
from envs.forecasting.cache import cache_root, predictor_fingerprint, recording_fingerprint
from envs.forecasting.resampling import resample_matrix, time_key
from envs.forecasting.sources import NoisyOracleForecast, split_of_recording
from envs.forecasting.window import PredictorForecast
from envs.replay import Replay


class UncertaintySource:
    """Radii ``(m, H)`` metres for the perceived pedestrians ``rows`` of a replay at ``t_s``."""

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        raise NotImplementedError

    def for_episode(self, replay: Replay, index: int) -> UncertaintySource:
        """The source to ask during one episode of ``replay`` whose first perceived annotation is ``index``: a source
        with state per episode (:class:`OnlineUncertainty`) starts a new one; the others are their own."""
        return self


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
    """Split conformal radii of a shipped forecast source (``cv``, ``cv_gaussian`` or shipped point weights) per
    recording's split.

    Args:
        name: ``cv``, ``cv_gaussian``, ``mesrnn``, ``srnn`` or ``vlstm``.
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

    def split_of(self, replay: Replay) -> str:
        """The split whose calibration serves ``replay`` (the one holding its recording out)."""
        return split_of_recording(replay.name) or self.default_split

    def gaussians(self, split: str, count: int) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
        """The forecasts' own Gaussians where the calibration scores them (``cv_gaussian``: ``sigma (count, P, 2)``,
        ``rho (count, P)``, the same for every pedestrian, as its head gives them), else ``(None, None)`` (a point
        forecast: the calibration's error model)."""
        if predictors.kind(self.name) != predictors.FITTED_BASELINE:
            return None, None
        from envs.forecasting.factory import load_learned

        step = np.asarray(load_learned(self.name, split, f"the {split!r} calibration").sigma_m(), np.float32)
        sigma = np.broadcast_to(step.astype(np.float64)[None, :, None], (count, len(step), 2))
        return sigma, np.zeros((count, len(step)))

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        split = self.split_of(replay)
        cal = self.calibration(split)
        speed = last_displacement(replay.positions, replay.present, index, rows)
        per_step = cal.radius_m(self.level, speed, *self.gaussians(split, len(rows)))  # (m, P) on the annotation grid
        return self.on_env_grid(per_step, replay.step_s, age_s)

    def on_env_grid(self, per_step: np.ndarray, step_s: float, age_s: float) -> np.ndarray:
        """Radii ``(m, P)`` on the annotation grid (0 at the annotation itself) resampled onto the environment's
        ``(m, H)`` (:func:`envs.forecasting.resampling.resample_matrix`, the forecasts' interpolation)."""
        key = (step_s, time_key(age_s))
        weights = self._weights.get(key)
        if weights is None:
            weights = self._weights[key] = resample_matrix(step_s, self.dt_s, self.horizon, per_step.shape[1], age_s)
        return per_step @ weights[:, 1:].T  # radius 0 at the annotation itself


def last_displacement(positions: np.ndarray, present: np.ndarray, index: int, rows: np.ndarray) -> np.ndarray:
    """``(m,)`` metres each of ``rows`` moved from annotation ``index − 1`` to ``index`` (0 unless at both) of
    ``positions (F, N, 2)``, ``present (F, N)``: the speed the error models read (metres per annotation step)."""
    if index < 1:
        return np.zeros(len(rows))
    both = present[index, rows] & present[index - 1, rows]
    disp = positions[index, rows] - positions[index - 1, rows]
    return np.where(both, np.hypot(disp[:, 0], disp[:, 1]), 0.0)


@dataclass
class _Forecasts:
    """The forecasts made at one annotation of an episode, waiting for their truth (:class:`_OnlineEpisode`).

    Attributes:
        frame: the annotation's index in the recording.
        columns: ``(n,)`` recording columns of the pedestrians present in all its observed frames.
        mean: ``(n, P, 2)`` their forecasts, metres; sigma: ``(n, P, 2)``, rho: ``(n, P)`` the Gaussians scored.
        alive: ``(n,)`` still present at every annotation since (the rows a revealed step scores).
        used: ``(K, P)`` the experts' thresholds at the annotation.
    """

    frame: int
    columns: np.ndarray
    mean: np.ndarray
    sigma: np.ndarray
    rho: np.ndarray
    alive: np.ndarray
    used: np.ndarray


class OnlineUncertainty(UncertaintySource):
    """Online conformal radii (``forecast_uncertainty_method="online"``; the module docstring): the thresholds of an
    :class:`~crowdnav_mesrnn.uncertainty.online_conformal.ExpertTracker` run over each episode, times the calibration's
    per-pedestrian unit, resampled as the split radii are.

    The radii belong to an episode: :meth:`for_episode` starts one (the environment does at every reset).

    Args:
        calibrated: the split radii of the same source (its calibrations, Gaussians and resampling).
        forecaster: the window forecasts of the environment, whose forecasts at every annotation are scored.
    """

    def __init__(self, calibrated: CalibratedUncertainty, forecaster: PredictorForecast) -> None:
        self.calibrated = calibrated
        self.forecaster = forecaster

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        raise RuntimeError("online radii belong to an episode: ask the source of for_episode(replay, index)")

    def for_episode(self, replay: Replay, index: int) -> UncertaintySource:
        return _OnlineEpisode(self, replay, index)


class _OnlineEpisode(UncertaintySource):
    """One episode's online radii (:class:`OnlineUncertainty`), its tracker advanced annotation by annotation."""

    def __init__(self, source: OnlineUncertainty, replay: Replay, index: int) -> None:
        from crowdnav_mesrnn.uncertainty.online_conformal import GAMMA_GRID, ExpertTracker

        self.source = source
        self.replay = replay
        self.recording = replay.recording
        # the replay is a slice of its recording: its annotation i is the recording's frame offset + i
        self.offset = int(np.searchsorted(self.recording.times_s(), replay.times[0]))
        self.split = source.calibrated.split_of(replay)
        self.calibration = source.calibrated.calibration(self.split)
        level = source.calibrated.level
        self.tracker = ExpertTracker(self.calibration.threshold(level), level, GAMMA_GRID, "observed")
        self.first = self.offset + max(int(index), 0)
        self.next = self.first  # the next annotation to process
        self.pending: deque[_Forecasts] = deque()
        self.current = self.tracker.thresholds()

    def thresholds_at(self, index: int) -> np.ndarray:
        """``(P,)`` the thresholds used at the replay's annotation ``index`` (processing every annotation up to it)."""
        frame = self.offset + int(index)
        if frame < self.next - 1:
            raise ValueError(f"annotation {index} lies before the latest one the episode's tracker has processed")
        while self.next <= frame:
            self._advance(self.next)
            self.next += 1
        return self.current

    def radius(self, replay: Replay, t_s: float, rows: np.ndarray, age_s: float, index: int) -> np.ndarray:
        if replay is not self.replay:
            raise ValueError(f"this episode's online radii are of replay {self.replay.name!r}, not {replay.name!r}")
        q = self.thresholds_at(max(int(index), 0))
        speed = last_displacement(replay.positions, replay.present, index, rows)
        unit = self.calibration.unit_m(speed, *self.source.calibrated.gaussians(self.split, len(rows)))
        return self.source.calibrated.on_env_grid(q[None, :] * unit, replay.step_s, age_s)

    def _advance(self, k: int) -> None:
        """Annotation ``k`` of the recording: score the earlier forecasts whose step it reveals, then record its own."""
        from crowdnav_mesrnn.models import gaussian

        rec = self.recording
        horizon = len(self.current)
        for made in self.pending:
            step = k - made.frame  # 1..P
            made.alive &= rec.present[k, made.columns]
            if made.alive.any():
                err = rec.positions[k, made.columns[made.alive]].astype(np.float64) - made.mean[made.alive, step - 1]
                d2 = gaussian.squared_mahalanobis(err, made.sigma[made.alive, step - 1], made.rho[made.alive, step - 1])
                self.tracker.reveal(step - 1, np.sqrt(d2), made.used[:, step - 1])
        while self.pending and k - self.pending[0].frame >= horizon:
            self.pending.popleft()
        lo = k - OBS_LEN + 1
        if lo >= 0:
            columns, mean = self.source.forecaster.frame_forecasts(rec, k)
            observed = rec.present[lo : k + 1][:, columns].all(axis=0)
            columns, mean = columns[observed], np.asarray(mean[observed], np.float64)
            if len(columns):
                speed = last_displacement(rec.positions, rec.present, k, columns)
                sigma, rho = self.source.calibrated.gaussians(self.split, len(columns))
                if sigma is None or rho is None:  # a point forecast: the error model's isotropic Gaussian
                    assert self.calibration.error_model is not None
                    s = self.calibration.error_model.sigma(speed)
                    sigma, rho = np.repeat(s[..., None], 2, axis=-1), np.zeros_like(s)
                alive = np.ones(len(columns), dtype=bool)
                self.pending.append(_Forecasts(k, columns, mean, sigma, rho, alive, self.tracker.experts))
        self.current = self.tracker.thresholds()


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

    With ``forecast_uncertainty_method="online"`` the calibrated sources' thresholds are tracked inside each episode
    (:class:`OnlineUncertainty`); the oracle's and the noisy oracle's radii have no thresholds to track.

    Raises:
        ConfigError: a predictor object, a plug-in or ``none`` (no calibration), ``carried`` forecasts, or ``online``
            thresholds with pedestrians who react.
    """
    level, dt_s, horizon = config.forecast_uncertainty_level, config.dt_s, config.horizon_steps
    calibrated = (predictors.BASELINE, predictors.FITTED_BASELINE, predictors.PRETRAINED)
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
        split_radii = CalibratedUncertainty(name, config.split, level, dt_s, horizon, cache_dir, config.data_dir)
        if config.forecast_uncertainty_method == "split":
            return split_radii
        if config.reaction != "none" or not isinstance(forecaster, PredictorForecast):
            raise ConfigError(
                f"config key 'forecast_uncertainty_method' = 'online' scores the window forecasts of the recorded "
                f"histories against the recording: it needs reaction 'none' (got {config.reaction!r})"
            )
        return OnlineUncertainty(split_radii, forecaster)
    raise ConfigError(f"forecast_uncertainty has nothing to measure for predictor {name!r} (no forecasts)")
