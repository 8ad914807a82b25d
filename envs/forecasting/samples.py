"""Sampled futures for the observation (``forecast_samples = S > 0``): ``S`` futures of each observed pedestrian drawn
from the forecast source's distribution, for planners that weigh plans against them (the search planner's
``samples`` option, :mod:`agents.planners.search`).

**Which distribution.** ``mesrnn``, ``srnn`` and ``vlstm``: the Gaussian head of the same model (its shipped
``gaussian`` weights of the split holding the recording out, beside the point weights whose forecasts fill
``forecasts``); ``cv_gaussian``: its own Gaussian around the constant-velocity forecast. Each step of each pedestrian is
``N(mean, Σ)`` of the head's mean rollout from the last ``obs_len`` annotations up to the perceived one (window
forecasts: causal, as the point forecasts are).

**How they are drawn.** By the head's own sampler, :meth:`crowdnav_mesrnn.models.gaussian.GaussianForecast.draw`,
``coherent`` (one standard normal draw per sample and pedestrian shared by every step: each sample is a trajectory
at one quantile of every step's Gaussian, as ``crowdnav-mesrnn predictor evaluate --samples`` draws by default). The
seed is a digest of the recording and the environment time, so the same time of the same recording gets the same
samples in every episode, arm, process and run, whoever else is perceived (every pedestrian of the frame is drawn,
then the observed ones are taken). The samples are on the annotation grid and resampled onto ``t + h * dt_s`` with
the forecasts' linear interpolation (the annotated position at the grid's origin).

**Computed once.** The Gaussians depend only on (weights, recording, annotation frame), so they are kept like the point
forecasts: per chunk of frames in memory and in the shared disk cache (:class:`GaussianTable` turns a distribution
into a table of ``3 P`` "steps" the window source keeps); only the draws are made at each step.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from envs.config import CrowdNavConfig
from envs.forecasting.cache import predictor_fingerprint
from envs.forecasting.factory import forecast_store, load_learned
from envs.forecasting.resampling import time_key
from envs.forecasting.sources import ForecastSource, split_of_recording
from envs.forecasting.window import PredictorForecast
from envs.replay import Replay

#: Forecast-source kinds with a distribution to sample (:func:`crowdnav_mesrnn.predictors.kind`).
SAMPLED_KINDS: Final[tuple[str, ...]] = (predictors.FITTED_BASELINE, predictors.PRETRAINED)


class GaussianTable:
    """A distribution predictor as a point predictor of ``3 P`` steps, so that the window source keeps its Gaussians
    (per frame, per chunk, on disk): steps ``1..P`` hold the mean, ``P+1..2P`` the scales ``(σx, σy)`` and
    ``2P+1..3P`` the correlation ``(ρ, 0)``, metres, float32.

    Args:
        model: an object with ``forecast_distribution(history, mask) -> (mean, sigma, rho)``
            (:class:`crowdnav_mesrnn.predictors.DistributionPredictor`), ``name``, ``obs_len`` and ``pred_len``.
    """

    def __init__(self, model: Any) -> None:
        self.model = model
        self.name = f"{model.name}-gaussian"
        self.obs_len = int(model.obs_len)
        self.steps = int(model.pred_len)
        self.pred_len = 3 * self.steps

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        mean, sigma, rho = self.model.forecast_distribution(history, mask)
        rho2 = np.stack([rho, np.zeros_like(rho)], axis=-1)
        return np.concatenate([mean, sigma, rho2], axis=1).astype(np.float32)

    def cache_fingerprint(self) -> str:
        """The distribution's weights, marked as this table (never read as the point forecasts of the same weights)."""
        return hashlib.sha256(f"gaussian-table:{predictor_fingerprint(self.model)}".encode()).hexdigest()


def sample_seed(recording: str, t_s: float) -> int:
    """The seed of the draws at env time ``t_s`` of ``recording``: 63 bits of a digest of both."""
    digest = hashlib.sha256(f"forecast-samples:{recording}:{time_key(t_s)}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2**63 - 1)


class SampleSource:
    """``S`` sampled futures of the perceived pedestrians (the module docstring).

    Args:
        name: the forecast source (``mesrnn``, ``srnn``, ``vlstm``, ``cv_gaussian``).
        table: the window source of the distributions (:class:`GaussianTable` predictors per recording).
        samples: ``S``.
    """

    def __init__(self, name: str, table: PredictorForecast, samples: int) -> None:
        self.name = name
        self.table = table
        self.samples = int(samples)
        self.horizon = table.horizon

    def draw(self, replay: Replay, t_s: float, rows: np.ndarray) -> np.ndarray:
        """``(len(rows), S, H, 2)`` world positions at ``t + h * dt_s`` (h = 1..H) of ``S`` futures of each of the
        perceived pedestrians ``rows`` of ``replay``, float64 metres."""
        import torch  # the environment imports torch only where a predictor needs it

        from crowdnav_mesrnn.models.gaussian import GaussianForecast

        out = np.zeros((len(rows), self.samples, self.horizon, 2))
        if len(rows) == 0:
            return out
        rec = replay.recording
        at = self.table.frame_at(rec, t_s)
        cols, table = (np.zeros(0, np.int64), None) if at is None else self.table.frame_forecasts(rec, at[0])
        want = replay.columns[rows]
        idx = np.minimum(np.searchsorted(cols, want), max(len(cols) - 1, 0))
        if at is None or table is None or not np.array_equal(cols[idx], want):
            raise RuntimeError(f"samples requested for pedestrians not perceived at t={t_s:.3f} s in {replay.name}")
        steps = table.shape[1] // 3
        dist = torch.from_numpy(np.array(table.transpose(1, 0, 2), dtype=np.float32))[None]  # (1, 3P, n, 2), a copy
        head = GaussianForecast(dist[:, :steps], dist[:, steps : 2 * steps], dist[:, 2 * steps :, :, 0])
        generator = torch.Generator().manual_seed(sample_seed(rec.name, t_s))
        drawn = head.draw(self.samples, generator, coherent=True)[0].numpy()  # (S, P, n, 2): every pedestrian
        drawn = drawn[:, :, idx].astype(np.float64).transpose(2, 0, 1, 3)  # (m, S, P, 2): the perceived ones
        weights = self.table.resample_weights(rec.step_s, steps, at[1])  # (H, P + 1)
        out = np.einsum("hp,mspc->mshc", weights[:, 1:], drawn)
        if weights[:, 0].any():  # the first env steps fall before the first forecast step: the annotated position
            out += weights[None, None, :, 0, None] * rec.positions[at[0], want][:, None, None, :]
        return out


def make_sample_source(
    config: CrowdNavConfig, recordings: Sequence[str], forecaster: ForecastSource, predictor: Any = None
) -> SampleSource:
    """The sampled futures ``config`` asks for (``forecast_samples`` > 0) beside the forecast source ``forecaster``: the
    distribution of ``config.predictor`` per recording's split (the one holding it out; ``config.split`` for other
    recordings), kept like the forecasts (``cache_forecasts``, ``forecast_disk_cache``).

    Raises:
        ConfigError: a predictor object or a source without a distribution (naming the ones with one), carried
            forecasts, or pedestrians who react.
        PredictorUnavailableError: a distribution could not be loaded
            (:func:`envs.forecasting.factory.load_learned`).
    """
    name = config.predictor
    with_distribution = predictors.names(*SAMPLED_KINDS, plugins=False)
    if predictor is not None or predictors.kind(name) not in SAMPLED_KINDS:
        given = repr(getattr(predictor, "name", "a predictor object")) if predictor is not None else repr(name)
        raise ConfigError(
            f"config key 'forecast_samples' = {config.forecast_samples!r} needs a forecast source with a distribution "
            f"({', '.join(with_distribution)}); predictor {given} has none"
        )
    if forecaster.memory != "window" or config.reaction != "none":
        raise ConfigError(
            f"config key 'forecast_samples' draws from window forecasts of the recorded histories: it needs "
            f"forecast_memory 'window' and reaction 'none' (got {config.forecast_memory!r}, {config.reaction!r})"
        )
    per_recording: dict[str, Any] = {}
    default = None
    for rec in recordings:
        split = split_of_recording(rec)
        if split is None:
            default = GaussianTable(load_learned(name, config.split, rec, head="gaussian"))
        else:
            per_recording[rec] = GaussianTable(load_learned(name, split, rec, head="gaussian"))
    table = PredictorForecast(
        f"{name} distribution",
        per_recording,
        default,
        config.dt_s,
        config.horizon_steps,
        config.cache_forecasts,
        forecast_store(config),
    )
    return SampleSource(name, table, config.forecast_samples)
