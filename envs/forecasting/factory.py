"""Building a forecast source from the env config and the predictor registry.

:func:`make_forecast_source` asks :mod:`crowdnav_mesrnn.predictors` what the configured name is (its kind) and
builds the matching source, loading a predictor per split where the kind asks for it: a recording is forecast by
the predictor of the split holding it out (never one trained on it). A predictor that cannot be loaded is a
:class:`PredictorUnavailableError` saying what was needed and how to get it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Final

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from envs.config import FORECAST_MEMORIES, CrowdNavConfig
from envs.forecasting.cache import ForecastStore, cache_root
from envs.forecasting.carried import CarriedPredictorForecast
from envs.forecasting.sources import (
    ForecastModel,
    ForecastSource,
    NoForecast,
    NoisyOracleForecast,
    OracleForecast,
    split_of_recording,
)
from envs.forecasting.threads import fork_safe_torch
from envs.forecasting.window import PredictorForecast


class PredictorUnavailableError(FileNotFoundError):
    """A pretrained predictor (its weights) could not be loaded; the message says what and how to get it."""


_LOADED: dict[tuple[str, str, str], Any] = {}


def _without_weights() -> str:
    """The forecast sources that need no weights, quoted: ``'cv', 'oracle', 'noisy_oracle' or 'none'``."""
    kinds = (predictors.BASELINE, predictors.TRUTH, predictors.NOISY_TRUTH)
    quoted = [repr(n) for n in (*predictors.names(*kinds, plugins=False), *predictors.names(predictors.NO_FORECAST))]
    return f"{', '.join(quoted[:-1])} or {quoted[-1]}"


WEIGHTS_HELP: Final[str] = (
    "Pretrained weights are looked up by crowdnav_mesrnn.models.pretrained.load_pretrained (package data in "
    "crowdnav_mesrnn/pretrained/); train them with the predictor commands of `crowdnav-mesrnn --help`. To run "
    f"without them choose predictor={_without_weights()} (e.g. gymnasium.make('CrowdNav-CV-v0')), "
    "or pass your own predictor object as predictor=..."
)


def load_learned(name: str, split: str, needed_for: str, head: str = "point") -> Any:
    """The predictor ``name`` of ``split`` (:func:`crowdnav_mesrnn.predictors.load`), one object per process; with
    ``head="gaussian"`` its distribution (a structural RNN's Gaussian-head weights, ``cv_gaussian`` itself:
    :func:`crowdnav_mesrnn.evaluation.protocol.load_shipped`).

    Raises:
        PredictorUnavailableError: naming the model, the split, the recording it was needed for,
            the underlying error and how to get the weights.
    """
    key = (name, split, head)
    if key not in _LOADED:
        try:
            if head == "point":
                _LOADED[key] = predictors.load(name, split)
            else:
                from crowdnav_mesrnn.evaluation.protocol import load_shipped

                _LOADED[key] = load_shipped(name, split, head=head)
        except Exception as exc:  # any failure to load is reported the same way, with its cause
            shipped = predictors.kind(name) in (predictors.PRETRAINED, predictors.FITTED_BASELINE)
            what = "predictor" if head == "point" else f"{head} distribution"
            raise PredictorUnavailableError(
                f"the {'pretrained ' if shipped else 'plug-in '}{name!r} {what} for split {split!r} (needed to "
                f"forecast {needed_for}) could not be loaded: {type(exc).__name__}: {str(exc).rstrip('.')}. "
                + (WEIGHTS_HELP if shipped else "See crowdnav_mesrnn.predictors for the plug-in protocol.")
            ) from exc
    return _LOADED[key]


def forecast_store(config: CrowdNavConfig) -> ForecastStore | None:
    """The shared disk cache ``config`` asks for (``forecast_disk_cache``, in ``forecast_cache_dir``), or None."""
    return ForecastStore(cache_root(config.forecast_cache_dir)) if config.forecast_disk_cache else None


def make_forecast_source(
    config: CrowdNavConfig, recordings: Sequence[str], predictor: ForecastModel | None = None
) -> ForecastSource:
    """The forecast source of ``config`` for a set of recordings.

    The kind of ``config.predictor`` (:func:`crowdnav_mesrnn.predictors.kind`) chooses the source: none, the oracle,
    the noisy oracle (``noisy_oracle_ade_m``), a weightless baseline loaded once, or a predictor loaded per split
    (the fitted baseline ``cv_gaussian``, the pretrained and the plug-ins), window or carried (``forecast_memory``;
    the baselines are always window) and shared through the disk cache (:func:`forecast_store`; keyed on the
    predictor's ``cache_fingerprint()`` where it has one). Forecasts are on the grid ``dt_s`` x
    ``horizon_steps`` and kept in memory with ``cache_forecasts``.

    Args:
        config: the environment's configuration.
        recordings: names of the recordings episodes may replay; each is forecast by the predictor of the split
            holding it out, a recording outside every split's test part (synthetic, scripted crowds) by that of
            ``config.split``.
        predictor: a predictor object used for every recording instead of ``config.predictor``.

    Raises:
        ConfigError: an unknown ``forecast_memory`` or ``predictor`` name; ``predictor`` without a ``forecast``
            method; ``carried`` with a predictor object (or loaded predictor) without ``online(num_slots)``.
        PredictorUnavailableError: a predictor of a split could not be loaded.
    """
    memory = config.forecast_memory
    if memory not in FORECAST_MEMORIES:
        raise ConfigError(f"unknown forecast_memory {memory!r}; valid: {', '.join(FORECAST_MEMORIES)}")
    fork_safe_torch()
    dt_s, horizon, cache = config.dt_s, config.horizon_steps, config.cache_forecasts
    learned_cls = CarriedPredictorForecast if memory == "carried" else PredictorForecast
    if predictor is not None:
        if not callable(getattr(predictor, "forecast", None)):
            raise ConfigError(
                f"predictor must be one of {', '.join(predictors.names(plugins=False))} or an object with a "
                f"forecast(history, mask) method, got {predictor!r}"
            )
        name = str(getattr(predictor, "name", "custom"))
        return learned_cls(name, {}, predictor, dt_s, horizon, cache, forecast_store(config))
    name = config.predictor
    kind = predictors.kind(name)  # raises ConfigError listing the valid names
    if kind == predictors.NO_FORECAST:
        return NoForecast()
    if kind == predictors.TRUTH:
        return OracleForecast()
    if kind == predictors.NOISY_TRUTH:
        return NoisyOracleForecast(config.noisy_oracle_ade_m, horizon)
    if kind == predictors.BASELINE:
        return PredictorForecast(name, {}, predictors.load(name), dt_s, horizon, cache)
    if kind == predictors.FITTED_BASELINE:  # constant velocity keeps no state to carry
        learned_cls = PredictorForecast
    per_recording: dict[str, ForecastModel] = {}
    default: ForecastModel | None = None
    for rec in recordings:
        split = split_of_recording(rec)
        if split is None:
            default = load_learned(name, config.split, rec)
        else:
            per_recording[rec] = load_learned(name, split, rec)
    return learned_cls(name, per_recording, default, dt_s, horizon, cache, forecast_store(config))
