"""Block bootstrap intervals for paired ADE/FDE differences, on inputs whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sps

from crowdnav_mesrnn.evaluation.statistics import (
    PairedErrors,
    SeededErrors,
    average_ci,
    block_bootstrap_ci,
    block_bootstrap_replicates,
    seeded_average_ci,
    seeded_difference_ci,
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
def per_seed(values: list[float], counts: np.ndarray) -> SeededErrors:
    """Seed k's error is values[k] for every pedestrian of every window: no window variance."""
    return SeededErrors(np.array([v * counts for v in values]), counts)


def test_one_seed_each_is_the_block_bootstrap() -> None:
    rng = np.random.default_rng(4)
    pairs, paired = [], {}
    for s in range(5):
        counts = rng.integers(1, 6, 137 + s)
        a, b = rng.normal(0.5, 0.1, len(counts)) * counts, rng.normal(0.45, 0.1, len(counts)) * counts
        pairs.append((SeededErrors(a, counts), SeededErrors(b, counts)))
        paired[s] = PairedErrors(a - b, counts)
    d = seeded_difference_ci(*pairs[0], 20, 3000, seed=7)
    assert d.interval == block_bootstrap_ci(paired[0], 20, 3000, seed=7) and d.seed_se == 0.0
    assert d.estimate == pytest.approx(paired[0].estimate) and d.df == float("inf") and d.window_se > 0
    avg = seeded_average_ci(pairs, 20, 3000, seed=2)
    est, ci = average_ci(paired, 20, 3000, seed=2)
    assert avg.interval == ci and avg.estimate == pytest.approx(est)


def test_seed_part_is_welch_on_the_per_seed_errors() -> None:
    counts = np.array([1, 4, 2, 7, 3, 3, 5, 1, 1, 2])
    # Two seeds at 1 and 3 against a deterministic 0: mean 2, s² = 2, se = 1, one degree of freedom.
    d = seeded_difference_ci(per_seed([1.0, 3.0], counts), per_seed([0.0], counts), n_resamples=500)
    assert d.estimate == pytest.approx(2.0) and d.seed_se == pytest.approx(1.0) and d.window_se == 0.0
    assert d.df == pytest.approx(1.0)
    assert d.interval[1] - 2.0 == pytest.approx(12.7062, abs=1e-4)  # t(1) quantile 0.975
    # Three seeds each: exactly scipy's Welch interval on the per-seed errors.
    a, b = [0.41, 0.44, 0.43], [0.47, 0.45, 0.52]
    d = seeded_difference_ci(per_seed(a, counts), per_seed(b, counts), n_resamples=500)
    ref = sps.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    assert d.interval == pytest.approx((ref.low, ref.high)) and d.estimate == pytest.approx(np.mean(a) - np.mean(b))


def test_per_seed_errors_are_pedestrian_weighted() -> None:
    """Seed 0: window 0 (one pedestrian) error 2, window 1 (three) error 0 -> 0.5, not the mean 1."""
    counts = np.array([1, 3])
    a = SeededErrors(np.array([[2.0, 0.0], [0.5, 1.5]]), counts)
    assert a.estimate == pytest.approx(0.5)
    d = seeded_difference_ci(a, per_seed([0.0], counts), n_resamples=200)
    assert d.estimate == pytest.approx(0.5) and d.seed_se == 0.0  # both seeds are at 0.5 overall


def test_the_average_counts_seed_effects_shared_across_splits() -> None:
    counts = np.full(40, 2)
    shared = [(per_seed([0.4, 0.5, 0.6], counts), per_seed([0.5], counts)) for _ in range(5)]
    one = seeded_difference_ci(*shared[0], n_resamples=300)
    avg = seeded_average_ci(shared, n_resamples=300)
    # Seed 0 is the best on every split: averaging over splits does not shrink the seed part.
    assert avg.seed_se == pytest.approx(one.seed_se) and avg.df == pytest.approx(2.0)
    rotated = [(per_seed(list(np.roll([0.4, 0.5, 0.6], k)), counts), per_seed([0.5], counts)) for k in range(5)]
    assert seeded_average_ci(rotated, n_resamples=300).seed_se < one.seed_se / 3
    with pytest.raises(ValueError, match="same seeds on every split"):
        seeded_average_ci([shared[0], (per_seed([0.4, 0.5], counts), per_seed([0.5], counts))])


@pytest.mark.parametrize(("seeds_b", "splits"), [(1, 1), (3, 1), (3, 5)])
def test_coverage_when_seeds_dominate(seeds_b: int, splits: int) -> None:
    """No true difference; seed noise (sd 0.05) dominates window noise. Resampling three seeds covered
    about 75-87 % here; the t interval must cover about 95 %."""
    rng = np.random.default_rng(11)
    w, trials, hits = 60, 300, 0
    counts = rng.integers(1, 5, w)
    for _ in range(trials):
        pairs = []
        for _ in range(splits):
            window = np.convolve(rng.normal(0, 0.01, w + 19), np.ones(20) / 20, mode="valid")
            a = [(0.5 + rng.normal(0, 0.05) + window) * counts for _ in range(3)]
            b = [(0.5 + rng.normal(0, 0.05 if seeds_b > 1 else 0.0) + window) * counts for _ in range(seeds_b)]
            pairs.append((SeededErrors(np.array(a), counts), SeededErrors(np.array(b), counts)))
        d = (
            seeded_difference_ci(*pairs[0], n_resamples=200)
            if splits == 1
            else seeded_average_ci(pairs, n_resamples=200)
        )
        hits += d.interval[0] <= 0.0 <= d.interval[1]
    assert 0.9 <= hits / trials <= 0.99


def test_seeded_errors_are_checked() -> None:
    with pytest.raises(ValueError, match="different windows"):
        seeded_difference_ci(SeededErrors(np.ones((2, 3)), np.ones(3)), SeededErrors(np.ones(3), np.array([1, 2, 1])))
    with pytest.raises(ValueError, match="seeds, windows"):
        SeededErrors(np.ones((2, 3)), np.ones(4))
    with pytest.raises(ValueError, match="positive pedestrian count"):
        SeededErrors(np.ones(2), np.array([1, 0]))
