"""The expert mixture one window at a time (:class:`ExpertTracker`): driven along a stream with the reveal rule's
clock it gives :func:`aggregate_thresholds`' thresholds and final weights."""

from __future__ import annotations

import numpy as np
import pytest

from crowdnav_mesrnn.uncertainty.online_conformal import (
    GAMMA_GRID,
    REVEAL_RULES,
    ExpertTracker,
    _revealed_before,
    aggregate_thresholds,
)


def drive(
    scores: np.ndarray, window: np.ndarray, time: np.ndarray, start: np.ndarray, reveal: str
) -> tuple[np.ndarray, np.ndarray]:
    """``(W, P)`` thresholds and ``(P, K)`` final weights of an :class:`ExpertTracker` fed the stream window by
    window: at each forecast time, first every outcome revealed by then (the same reveal rule), then the thresholds."""
    tracker = ExpertTracker(start, 0.9, GAMMA_GRID, reveal)
    steps = len(start)
    revealed = [
        _revealed_before(scores[:, j], window, time, tracker.delays[j], reveal) for j in range(steps)
    ]  # the batch's own schedule of which window is revealed when
    used = np.empty((len(time), len(GAMMA_GRID), steps))
    out = np.empty((len(time), steps))
    for k in range(len(time)):
        for j in range(steps):
            _, now = next(revealed[j])
            for i, rows in now:
                tracker.reveal(j, rows, used[i][:, j])
        used[k] = tracker.experts
        out[k] = tracker.thresholds()
    return out, tracker.weights


@pytest.mark.parametrize("reveal", REVEAL_RULES)
def test_one_window_at_a_time_equals_the_batch_mixture(reveal: str) -> None:
    rng = np.random.default_rng(3)
    per = rng.integers(0, 4, 120)
    window = np.repeat(np.arange(120), per)
    scores = rng.rayleigh(1.4, size=(len(window), 12))
    if reveal == "observed":
        scores[rng.uniform(size=scores.shape) < 0.2] = np.nan
    time = np.cumsum(rng.integers(1, 3, 120))
    start = np.linspace(1.0, 3.0, 12)
    start[3], start[5] = np.inf, 0.0
    expected, weights = aggregate_thresholds(scores, window, time, start, 0.9, GAMMA_GRID, reveal)
    got, got_weights = drive(scores, window, time, start, reveal)
    # equal up to the order BLAS sums the weighted mean in (the same order here: the tracker keeps its columns strided)
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=0)
    np.testing.assert_allclose(got_weights, weights, rtol=1e-13, atol=0)


def test_a_tracker_that_misses_too_often_widens_and_one_that_over_covers_narrows() -> None:
    for scale, direction in ((3.0, 1.0), (0.3, -1.0)):
        tracker = ExpertTracker(np.ones(12), 0.9)
        for _ in range(60):
            used = tracker.experts
            for j in range(12):
                tracker.reveal(j, np.full(5, scale), used[:, j])
        assert np.all(direction * (tracker.thresholds() - 1.0) > 0)


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="level"):
        ExpertTracker(np.ones(12), 1.0)
    with pytest.raises(ValueError, match="reveal rule"):
        ExpertTracker(np.ones(12), 0.9, reveal="later")
