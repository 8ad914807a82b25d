"""Building a forecast source: the name asked of the predictor registry, the predictors loaded per split.

:func:`make_forecast_source` asks :mod:`crowdnav_mesrnn.predictors` what the configured name is and builds the
matching source; a recording is forecast by the predictor of the split holding it out (never one trained on it).
A predictor that cannot be loaded is a :class:`PredictorUnavailableError` saying what was needed and how to get it.
"""

from __future__ import annotations

from typing import Any, Final

from crowdnav_mesrnn.config import ConfigError
from envs.config import FORECAST_MEMORIES, FORECAST_SOURCES, LEARNED_SOURCES, check_predictor_name, is_plugin_source
from envs.forecasting.cache import ForecastStore
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


_LOADED: dict[tuple[str, str], Any] = {}

WEIGHTS_HELP: Final[str] = (
    "Pretrained weights are looked up by crowdnav_mesrnn.models.pretrained.load_pretrained (package data in "
    "crowdnav_mesrnn/pretrained/); train them with the predictor commands of `crowdnav-mesrnn --help`. To run "
    "without them choose predictor='cv', 'oracle', 'noisy_oracle' or 'none' (e.g. gymnasium.make('CrowdNav-CV-v0')), "
    "or pass your own predictor object as predictor=..."
)


def load_learned(name: str, split: str, needed_for: str) -> Any:
    """The pretrained ``name`` predictor of ``split`` (cached per process).

    Raises:
        PredictorUnavailableError: naming the model, the split, the recording it was needed for,
            the underlying error and how to get the weights.
    """
    key = (name, split)
    if key not in _LOADED:
        from crowdnav_mesrnn import models

        try:
            _LOADED[key] = models.get_predictor(name, split)
        except Exception as exc:  # any failure to load is reported the same way, with its cause
            shipped = name in LEARNED_SOURCES
            raise PredictorUnavailableError(
                f"the {'pretrained ' if shipped else 'plug-in '}{name!r} predictor for split {split!r} (needed to "
                f"forecast {needed_for}) could not be loaded: {type(exc).__name__}: {str(exc).rstrip('.')}. "
                + (WEIGHTS_HELP if shipped else "See crowdnav_mesrnn.predictors for the plug-in protocol.")
            ) from exc
    return _LOADED[key]


def make_forecast_source(
    predictor: str | ForecastModel,
    recordings: list[str],
    default_split: str,
    dt_s: float,
    horizon: int,
    cache: bool,
    noisy_oracle_ade_m: float,
    memory: str = "window",
    store: ForecastStore | None = None,
) -> ForecastSource:
    """The forecast source for a set of recordings.

    Args:
        predictor: a source name or a predictor object (used for every recording).
        recordings: names of the recordings episodes may replay.
        default_split: split whose predictor forecasts recordings that belong to no split's test
            part (synthetic, scripted crowds).
        dt_s: environment step, seconds.
        horizon: H.
        cache: keep forecasts (per chunk of annotation frames, and resampled per time).
        noisy_oracle_ade_m: target ADE of ``noisy_oracle``.
        memory: ``window`` or ``carried`` (see :attr:`envs.config.CrowdNavConfig.forecast_memory`); ignored by
            ``none``, ``cv``, ``oracle`` and ``noisy_oracle``.
        store: the shared disk cache for predictors with weights (None: memory only).

    Raises:
        ConfigError: ``carried`` with a predictor object (or loaded predictor) without ``online(num_slots)``.
    """
    if memory not in FORECAST_MEMORIES:
        raise ConfigError(f"unknown forecast_memory {memory!r}; valid: {', '.join(FORECAST_MEMORIES)}")
    fork_safe_torch()
    learned_cls = CarriedPredictorForecast if memory == "carried" else PredictorForecast
    if not isinstance(predictor, str):
        if not callable(getattr(predictor, "forecast", None)):
            raise ConfigError(
                f"predictor must be one of {', '.join(FORECAST_SOURCES)} or an object with a forecast(history, mask) "
                f"method, got {predictor!r}"
            )
        return learned_cls(str(getattr(predictor, "name", "custom")), {}, predictor, dt_s, horizon, cache, store)
    if predictor == "none":
        return NoForecast()
    if predictor == "oracle":
        return OracleForecast()
    if predictor == "noisy_oracle":
        return NoisyOracleForecast(noisy_oracle_ade_m, horizon)
    if predictor == "cv":
        from crowdnav_mesrnn.models import get_predictor

        return PredictorForecast("cv", {}, get_predictor("cv"), dt_s, horizon, cache)
    if predictor in LEARNED_SOURCES or is_plugin_source(predictor):  # a plug-in loads per split like MESRNN
        per_recording: dict[str, ForecastModel] = {}
        default: ForecastModel | None = None
        for rec in recordings:
            split = split_of_recording(rec)
            if split is None:
                default = load_learned(predictor, default_split, rec)
            else:
                per_recording[rec] = load_learned(predictor, split, rec)
        return learned_cls(predictor, per_recording, default, dt_s, horizon, cache, store)
    raise ValueError(check_predictor_name(predictor))  # raises ConfigError listing the valid names
