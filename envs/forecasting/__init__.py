"""Forecasts in the observation: sources, resampling, the shared cache, uncertainty radii, sampled futures.

One module per concern:

- :mod:`~envs.forecasting.sources`: the base class and the sources without a predictor (none, oracle, noisy oracle);
- :mod:`~envs.forecasting.window`: window forecasts of a predictor (a fresh rollout at every annotation frame);
- :mod:`~envs.forecasting.carried`: carried forecasts (hidden states kept per pedestrian);
- :mod:`~envs.forecasting.factory`: a source built from the env config and the predictor registry;
- :mod:`~envs.forecasting.resampling`: from the predictor's annotation grid to the environment's grid;
- :mod:`~envs.forecasting.cache`: forecasts computed once (the on-disk cache and the process-wide tables);
- :mod:`~envs.forecasting.build`: filling the disk cache ahead (``crowdnav-mesrnn forecasts build``);
- :mod:`~envs.forecasting.uncertainty`: calibrated radii around the forecasts (split or online thresholds);
- :mod:`~envs.forecasting.samples`: sampled futures from the source's distribution;
- :mod:`~envs.forecasting.threads`: torch threads while forecasting, and fork safety.

Forecasts are causal (from the latest annotation the robot perceives) and out-of-sample (a recording is forecast
by the predictor of the split holding it out); cached and online forecasts are identical, bit for bit.
"""

from envs.forecasting.build import build_forecast_cache
from envs.forecasting.factory import PredictorUnavailableError, make_forecast_source
from envs.forecasting.samples import SampleSource, make_sample_source
from envs.forecasting.sources import ForecastModel, ForecastSource, TrueFuture
from envs.forecasting.uncertainty import UncertaintySource, make_uncertainty_source

__all__ = [
    "ForecastModel",
    "ForecastSource",
    "PredictorUnavailableError",
    "SampleSource",
    "TrueFuture",
    "UncertaintySource",
    "build_forecast_cache",
    "make_forecast_source",
    "make_sample_source",
    "make_uncertainty_source",
]
