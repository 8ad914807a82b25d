"""Evaluation of trajectory predictors on ETH/UCY windows.

- :mod:`~crowdnav_mesrnn.evaluation.metrics`: batching, rollouts, per-window error sums, per-pedestrian forecasts.
- :mod:`~crowdnav_mesrnn.evaluation.protocol`: ADE/FDE per leave-one-out split and averaged, distribution metrics,
  paired differences between predictors (``crowdnav-mesrnn predictor evaluate``).
- :mod:`~crowdnav_mesrnn.evaluation.statistics`: block-bootstrap and seed-aware intervals.

The names this package held as a single module are still served from it, with a ``DeprecationWarning``.
"""

from __future__ import annotations

from crowdnav_mesrnn._deprecated import moved_attributes

_METRICS = "crowdnav_mesrnn.evaluation.metrics"
_PROTOCOL = "crowdnav_mesrnn.evaluation.protocol"

__getattr__ = moved_attributes(
    __name__,
    {
        **dict.fromkeys(
            (
                "BatchPredictFn",
                "DISTRIBUTION_KEYS",
                "DistributionFn",
                "METRIC_KEYS",
                "SampleFn",
                "ScoredForecasts",
                "batches",
                "collect_forecasts",
                "cv_predict_batch",
                "distribution_metrics",
                "evaluate_windows",
                "predicted_batches",
                "summarise",
                "window_errors",
            ),
            _METRICS,
        ),
        **dict.fromkeys(
            (
                "PAIRED_KEYS",
                "SAMPLINGS",
                "evaluate_model",
                "evaluate_versus",
                "format_result",
                "paired_differences",
                "paired_sums",
                "resolve_splits",
                "split_norm",
            ),
            _PROTOCOL,
        ),
    },
)
