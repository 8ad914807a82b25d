"""Block bootstrap intervals for paired ADE/FDE differences, on inputs whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sps

from crowdnav_mesrnn.stats import (
    PairedErrors,
    SeededErrors,
    average_ci,
    block_bootstrap_ci,
    block_bootstrap_replicates,
    seeded_average_ci,
    seeded_bootstrap_ci,
    seeded_bootstrap_replicates,
    verdict,
)


def unit(values: list[float] | np.ndarray) -> PairedErrors:
    v = np.asarray(values, dtype=float)
    return PairedErrors(v, np.ones_like(v))


def test_constant_difference_gives_a_zero_width_interval_at_that_value() -> None:
    counts = np.array([1, 4, 2, 7, 3, 3, 5])
    e = PairedErrors(-0.125 * counts, counts)
    for block_len in (1, 3, 20):
        lo, hi = block_bootstrap_ci(e, block_len=block_len, n_resamples=500)
        assert lo == pytest.approx(-0.125) and hi == pytest.approx(-0.125)
    est, (lo, hi) = average_ci({"a": e, "b": PairedErrors(0.5 * counts, counts)}, n_resamples=200)
    assert est == pytest.approx(0.1875) and lo == pytest.approx(0.1875) and hi == pytest.approx(0.1875)


def test_block_length_one_is_the_ordinary_bootstrap() -> None:
    x = np.random.default_rng(5).normal(0.1, 1.0, 200)
    reps = block_bootstrap_replicates(unit(x), block_len=1, n_resamples=4000, seed=3)
    # Exactly the draws of an ordinary bootstrap made with the same generator ...
    idx = np.random.default_rng(3).integers(0, len(x), size=(4000, len(x)))
    np.testing.assert_allclose(reps, x[idx].mean(1))
    # ... and the same interval as scipy's percentile bootstrap, up to Monte Carlo error.
    lo, hi = block_bootstrap_ci(unit(x), block_len=1, n_resamples=20_000, seed=1)
    ref = sps.bootstrap((x,), np.mean, n_resamples=20_000, method="percentile", random_state=2).confidence_interval
    width = ref.high - ref.low
    assert abs(lo - ref.low) < 0.05 * width and abs(hi - ref.high) < 0.05 * width


def test_hand_checked_blocks() -> None:
    """Four windows, blocks of two: the blocks are [1,2], [2,3], [3,4] (means 1.5, 2.5, 3.5) and a
    replicate averages two of them drawn with replacement: 1.5, 2, 2.5, 3, 3.5 with odds 1:2:3:2:1."""
    reps = block_bootstrap_replicates(unit([1.0, 2.0, 3.0, 4.0]), block_len=2, n_resamples=90_000, seed=0)
    values, counts = np.unique(np.round(reps, 9), return_counts=True)
    np.testing.assert_allclose(values, [1.5, 2.0, 2.5, 3.0, 3.5])
    np.testing.assert_allclose(counts / counts.sum(), np.array([1, 2, 3, 2, 1]) / 9, atol=0.01)


def test_last_block_is_cut_to_the_series_length() -> None:
    """Three windows, blocks of two: two blocks are drawn and the fourth window dropped, so a replicate
    is the first block plus the first window of the second: starts (0|1, 0|1) give means of
    [1,2,1], [1,2,2], [2,3,1], [2,3,2]."""
    reps = block_bootstrap_replicates(unit([1.0, 2.0, 3.0]), block_len=2, n_resamples=40_000, seed=1)
    values, counts = np.unique(np.round(reps, 9), return_counts=True)
    np.testing.assert_allclose(values, [4 / 3, 5 / 3, 2.0, 7 / 3])
    np.testing.assert_allclose(counts / counts.sum(), [0.25, 0.25, 0.25, 0.25], atol=0.01)


def test_pedestrian_weighted_ratio() -> None:
    """Window 0: one pedestrian, difference 2; window 1: three pedestrians, difference 0. The estimate
    is 2/4; ordinary-bootstrap replicates are 2 (w0 twice), 0 (w1 twice) or 2/4 (one each)."""
    e = PairedErrors(np.array([2.0, 0.0]), np.array([1, 3]))
    assert e.estimate == 0.5
    reps = block_bootstrap_replicates(e, block_len=1, n_resamples=40_000, seed=2)
    values, counts = np.unique(reps, return_counts=True)
    np.testing.assert_allclose(values, [0.0, 0.5, 2.0])
    np.testing.assert_allclose(counts / counts.sum(), [0.25, 0.5, 0.25], atol=0.01)


def test_blocks_widen_the_interval_of_a_correlated_series() -> None:
    rng = np.random.default_rng(0)
    x = np.convolve(rng.normal(0, 1, 620), np.ones(20) / 20, mode="valid")  # overlapping-window-like
    narrow = block_bootstrap_ci(unit(x), block_len=1, n_resamples=4000)
    wide = block_bootstrap_ci(unit(x), block_len=20, n_resamples=4000)
    assert wide[1] - wide[0] > 2 * (narrow[1] - narrow[0])


def test_verdicts_and_errors() -> None:
    assert verdict((-0.2, -0.01)) == "A better"
    assert verdict((0.01, 0.2)) == "B better"
    assert verdict((-0.01, 0.02)) == "no detectable difference"
    assert verdict((float("nan"), 1.0)) == "not computed"
    with pytest.raises(ValueError, match="block_len"):
        block_bootstrap_ci(unit([1.0]), block_len=0)
    with pytest.raises(ValueError, match="positive pedestrian count"):
        PairedErrors(np.array([1.0]), np.array([0]))
    # A block longer than the series uses the whole series: every replicate is the estimate.
    assert block_bootstrap_ci(unit([1.0, 3.0]), block_len=20, n_resamples=50) == (2.0, 2.0)


# ------------------------------------------------------------------ over training seeds
def test_one_seed_each_is_the_block_bootstrap_of_the_paired_difference() -> None:
    rng = np.random.default_rng(4)
    counts = rng.integers(1, 6, 137)
    a, b = rng.normal(0.5, 0.1, 137) * counts, rng.normal(0.45, 0.1, 137) * counts
    seeded = seeded_bootstrap_replicates(SeededErrors(a, counts), SeededErrors(b, counts), 20, 3000, seed=7)
    plain = block_bootstrap_replicates(PairedErrors(a - b, counts), 20, 3000, seed=7)
    np.testing.assert_allclose(seeded, plain, rtol=1e-12, atol=1e-12)


def test_hand_checked_seed_draws() -> None:
    """A has two seeds whose errors are 1 and 3 on every window, B one seed at 0: the windows drawn do
    not matter and a replicate is the mean of two seeds drawn with replacement, 1, 2 or 3 with odds 1:2:1."""
    w = 30
    a = SeededErrors(np.array([np.full(w, 1.0), np.full(w, 3.0)]), np.ones(w))
    b = SeededErrors(np.zeros((1, w)), np.ones(w))
    assert a.seeds == 2 and a.estimate == 2.0
    reps = seeded_bootstrap_replicates(a, b, block_len=5, n_resamples=40_000, seed=0)
    values, counts = np.unique(np.round(reps, 9), return_counts=True)
    np.testing.assert_allclose(values, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(counts / counts.sum(), [0.25, 0.5, 0.25], atol=0.01)
    est, (lo, hi) = seeded_bootstrap_ci(a, b, block_len=5, n_resamples=4000)
    assert est == 2.0 and lo == 1.0 and hi == 3.0


def test_seed_spread_widens_the_interval_and_the_average_combines_splits() -> None:
    rng = np.random.default_rng(1)
    w = 400
    noise = np.convolve(rng.normal(0, 0.05, w + 19), np.ones(20) / 20, mode="valid")
    counts = np.full(w, 2.0)
    b = SeededErrors(((0.5 + noise) * counts)[None], counts)
    same = SeededErrors(np.stack([(0.45 + noise) * counts] * 3), counts)
    spread = SeededErrors(np.stack([(0.45 + d + noise) * counts for d in (-0.04, 0.0, 0.04)]), counts)
    est1, ci1 = seeded_bootstrap_ci(same, b, n_resamples=3000)
    est2, ci2 = seeded_bootstrap_ci(spread, b, n_resamples=3000)
    assert est1 == pytest.approx(-0.05) and est2 == pytest.approx(-0.05)
    assert ci1[0] == pytest.approx(-0.05) and ci1[1] == pytest.approx(-0.05)  # same noise: zero width
    assert ci2[1] - ci2[0] > 0.03  # the seeds' spread (±0.04) is in the interval
    est, (lo, hi) = seeded_average_ci([(same, b), (spread, b)], n_resamples=3000)
    assert est == pytest.approx(-0.05) and lo < -0.05 < hi and hi - lo < ci2[1] - ci2[0]


def test_seeded_errors_are_checked() -> None:
    with pytest.raises(ValueError, match="different windows"):
        seeded_bootstrap_ci(SeededErrors(np.ones((2, 3)), np.ones(3)), SeededErrors(np.ones(3), np.array([1, 2, 1])))
    with pytest.raises(ValueError, match="seeds, windows"):
        SeededErrors(np.ones((2, 3)), np.ones(4))
    with pytest.raises(ValueError, match="positive pedestrian count"):
        SeededErrors(np.ones(2), np.array([1, 0]))
