"""Forecasts when pedestrians react to the robot: from the histories the robot observed, not the recording's.

Under ``reaction="none"`` the observed histories are the recorded ones, so a window predictor's forecasts depend only
on (predictor, recording, annotation frame) and come from the per-recording cache
(:class:`~envs.forecasting.window.PredictorForecast`). When people react, the tracker's record of the episode
(:class:`envs.reactive.ObservedReplay`) differs from the recording wherever someone was off it, and the rule is:

* a forecast at annotation frame ``i`` reads the histories of the ``obs_len`` annotation steps up to ``tau_i`` of
  every pedestrian seen in them (social predictors read their neighbours too). If no annotation in that window
  (one annotation step wider, for histories interpolated across a gap in the file) was recorded off the recording,
  every history the predictor reads is the recorded one: the cached forecast is the forecast
  (:func:`needs_observed`);
* otherwise the frame is forecast from the observed histories, for the whole scene at once, by the same call the
  online path makes (:func:`observed_forecasts`: one predictor call on the frame's histories, resampled onto the
  environment's grid exactly as the cache's are). A deviation therefore changes everyone's forecast while it is in
  the window (a social predictor's neighbours see it), and nobody's after.

Fed the recorded histories, :func:`observed_forecasts` gives the cached forecasts bit for bit
(``tests/envs/test_reaction_env.py``), so the two paths cannot disagree on unreacted histories. ``carried`` memory
(hidden states from each pedestrian's first appearance in the recording) has no such window and is refused with a
reaction model. ``oracle`` and ``noisy_oracle`` keep their meaning: the recorded future, what a person would have done
without the robot, a counterfactual once people react.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from envs.forecasting.cache import definition_key
from envs.forecasting.resampling import resample_matrix, time_key
from envs.forecasting.threads import fork_safe_torch, torch_threads
from envs.forecasting.window import PredictorForecast
from envs.replay import Replay

if TYPE_CHECKING:
    from envs.reactive import ObservedReplay


def needs_observed(source: PredictorForecast, observed: ObservedReplay, t_s: float) -> bool:
    """Whether the forecast at ``t_s`` must be computed from the observed histories: some annotation in its history
    window (plus one annotation step) was recorded off the recording.

    Args:
        source: the window predictor source.
        observed: the tracker's record of the episode.
        t_s: the environment's time, seconds.
    """
    perceived = observed.perceived_at(t_s)
    if perceived.index < 0:
        return False
    _, obs_len, _ = source._model_sizes(observed.recording)
    tau = perceived.time_s
    return observed.deviated_between(tau - obs_len * observed.step_s, tau)


def observed_forecasts(
    source: PredictorForecast,
    observed: Replay,
    t_s: float,
    rows: np.ndarray,
    memo: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> np.ndarray:
    """Forecasts of the perceived pedestrians ``rows`` at ``t_s`` from the observed histories.

    As the online path (:meth:`PredictorForecast.compute_frame`, then its resampling) on ``observed`` instead of the
    recording: the histories of the ``obs_len`` annotation steps up to the latest annotation ``tau`` at or before
    ``t_s`` of every pedestrian seen in them, one predictor call (on :attr:`PredictorForecast.threads` torch
    threads), the forecasts of those present at ``tau`` resampled onto ``t_s + h * dt_s``. A predictor that forecasts
    each pedestrian from its own history alone (constant velocity:
    :func:`~envs.forecasting.cache.definition_key`) gets only the histories of ``rows``: each row of its batch is what
    the whole scene's call gives it (as the cache's batched chunks rely on).

    Args:
        source: the window predictor source (its predictor for the recording, grid and threads).
        observed: the tracker's record of the episode (a :class:`~envs.replay.Replay`).
        t_s: the environment's time, seconds.
        rows: ``(m,)`` replay rows perceived at ``t_s``.
        memo: an episode's forecasts of a social predictor per annotation frame (final once computed: frames up to
            ``t_s`` are never rewritten), reused by later times reading the same frame (``biwi_eth``).

    Returns:
        ``(m, H, 2)`` world positions at ``t_s + h * dt_s``, metres.
    """
    if len(rows) == 0:
        return np.zeros((0, source.horizon, 2))
    rec = observed.recording
    model, _, pred_len = source._model_sizes(rec)
    perceived = observed.perceived_at(t_s)
    i, offset = perceived.index, perceived.age_s
    independent = definition_key(model) is not None
    held = None if (memo is None or independent) else memo.get(i)
    if held is None:
        cols, fc = _frame_forecasts(source, observed, i, rows if independent else None)
        if memo is not None and not independent:
            memo[i] = (cols, fc)
    else:
        cols, fc = held
    key = (float(rec.step_s), pred_len, time_key(offset))
    weights = source._weights.get(key)
    if weights is None:
        weights = source._weights[key] = resample_matrix(
            float(rec.step_s), source.dt_s, source.horizon, pred_len, offset
        )
    out = weights[:, 1:] @ fc.astype(np.float64)
    if weights[:, 0].any():  # the first env steps fall before the first forecast step: the annotated position
        out += weights[None, :, 0, None] * observed.positions[i, cols][:, None, :]
    idx = np.minimum(np.searchsorted(cols, rows), max(len(cols) - 1, 0))
    if len(cols) == 0 or not np.array_equal(cols[idx], rows):
        raise RuntimeError(f"forecast requested for pedestrians not observed at t={t_s:.3f} s in {observed.name}")
    return out[idx]


def _frame_forecasts(
    source: PredictorForecast, observed: Replay, i: int, rows: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """``(rows (n,), forecasts (n, P, 2) float32)`` at annotation ``i`` of ``observed`` of the pedestrians present
    there, as :meth:`PredictorForecast.compute_frame`: of every pedestrian seen in the history window, or (``rows``
    given, a predictor forecasting each pedestrian alone) of those."""
    rec = observed.recording
    model, obs_len, pred_len = source._model_sizes(rec)
    back = rec.step_s * np.arange(obs_len - 1, -1, -1)
    pos, present = observed.positions_at(observed.times[i] - back)
    if rows is not None:
        seen = np.unique(np.asarray(rows, dtype=np.int64))
    else:
        seen = np.flatnonzero(present.any(axis=0))
    mask = present[:, seen]
    history = pos[:, seen].astype(np.float32)
    history[~mask] = 0.0
    now = mask[-1]
    fork_safe_torch()
    with torch_threads(source.threads):
        pred = source._checked(model, np.asarray(model.forecast(history, mask)), len(seen), pred_len, rec, i, now)
    source.calls += 1
    return seen[now], np.ascontiguousarray(pred[now], dtype=np.float32)
