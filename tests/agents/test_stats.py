"""agents.stats against values computed by hand or from closed forms."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import stats as sps

from agents.stats import (
    VERDICTS,
    bootstrap_mean_ci,
    holm,
    mcnemar_difference_ci,
    mcnemar_exact,
    mcnemar_min_detectable_difference,
    paired_bootstrap_diff_ci,
    paired_seed_test,
    paired_verdict,
    welch_seed_test,
    wilcoxon_paired,
    wilson_interval,
)


def test_wilson_matches_closed_form() -> None:
    k, n = 8, 10
    z = sps.norm.ppf(0.975)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(centre - half, abs=1e-12)
    assert hi == pytest.approx(centre + half, abs=1e-12)
    assert (lo, hi) == pytest.approx((0.4901624715, 0.9433178485), abs=1e-9)


def test_wilson_edges() -> None:
    assert wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = wilson_interval(0, 20)
    assert lo == pytest.approx(0.0, abs=1e-12) and 0 < hi < 0.2
    lo, hi = wilson_interval(20, 20)
    assert hi == pytest.approx(1.0, abs=1e-12) and 0.8 < lo < 1
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(11, 10)


def test_bootstrap_degenerate_inputs_without_warnings() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert all(math.isnan(v) for v in bootstrap_mean_ci([]))
        assert all(math.isnan(v) for v in bootstrap_mean_ci([math.nan]))
        assert bootstrap_mean_ci([2.5]) == (2.5, 2.5)
        assert bootstrap_mean_ci([1.0] * 7) == (1.0, 1.0)
        lo, hi = bootstrap_mean_ci([0.0] * 99 + [1.0])  # nearly constant: still a finite interval
        assert 0.0 <= lo <= 0.01 <= hi <= 0.05


def test_bootstrap_covers_mean_and_is_seeded() -> None:
    x = np.random.default_rng(1).normal(3.0, 1.0, size=200)
    lo, hi = bootstrap_mean_ci(x)
    se = x.std(ddof=1) / math.sqrt(x.size)
    assert lo < x.mean() < hi
    assert hi - lo == pytest.approx(2 * 1.96 * se, rel=0.2)
    assert bootstrap_mean_ci(x, seed=3) == bootstrap_mean_ci(x, seed=3)
    # non-finite values are ignored
    assert bootstrap_mean_ci([*x, math.nan]) == (lo, hi)


def test_paired_bootstrap_diff_is_interval_of_differences() -> None:
    rng = np.random.default_rng(2)
    a = rng.normal(size=100)
    b = a - 0.5 + 0.01 * rng.normal(size=100)  # strongly paired: the interval is narrow around 0.5
    lo, hi = paired_bootstrap_diff_ci(a, b)
    assert lo < 0.5 < hi and hi - lo < 0.01
    assert paired_bootstrap_diff_ci(a, b) == bootstrap_mean_ci(a - b)


def test_mcnemar_exact_hand_value() -> None:
    # 9 pairs where only a succeeds, 1 where only b does, 5 + 5 concordant
    a = [1] * 9 + [0] + [1] * 5 + [0] * 5
    b = [0] * 9 + [1] + [1] * 5 + [0] * 5
    res = mcnemar_exact(a, b, intervals=("exact", "bootstrap"))
    assert (res["b10"], res["b01"], res["n"]) == (9, 1, 20)
    assert res["p_value"] == pytest.approx(0.021484375, abs=1e-12)  # 2 * binom.cdf(1, 10, 0.5)
    assert res["difference"] == pytest.approx(8 / 20)
    assert res["rate_a"] == pytest.approx(14 / 20) and res["rate_b"] == pytest.approx(6 / 20)
    lo, hi = res["difference_ci"]
    assert 0 < lo < 0.4 < hi
    # Clopper-Pearson for 9 of 10: lower bound solves P(X >= 9 | pi) = 0.025, upper P(X <= 9 | pi) = 0.025
    pi_lo = sps.beta.ppf(0.025, 9, 2)
    pi_hi = sps.beta.ppf(0.975, 10, 1)
    assert res["difference_exact_ci"] == pytest.approx([0.5 * (2 * pi_lo - 1), 0.5 * (2 * pi_hi - 1)])
    assert mcnemar_exact(a, b).keys() == res.keys() - {"difference_ci"}  # the exact interval only, by default


def test_mcnemar_no_discordance() -> None:
    res = mcnemar_exact([1, 0, 1], [1, 0, 1], intervals=("bootstrap", "exact"))
    assert res["p_value"] == 1.0 and res["difference"] == 0.0 and res["difference_ci"] == [0.0, 0.0]
    assert res["difference_exact_ci"] == [0.0, 0.0]
    assert mcnemar_exact([], [])["n"] == 0
    assert all(math.isnan(v) for v in mcnemar_exact([], [])["difference_exact_ci"])
    with pytest.raises(ValueError, match="unknown interval"):
        mcnemar_exact([1], [0], intervals=("wald",))


def test_the_issue_example_no_longer_contradicts_itself() -> None:
    """Issue 31: "kalman - cv | -15.0 [-40.0, -5.0] | p 0.25" -- 3 discordant pairs of 20, all against a. The paired
    bootstrap interval excludes 0 beside a test that does not reject; the exact conditional interval does not."""
    a = [0] * 3 + [1] * 10 + [0] * 7
    b = [1] * 3 + [1] * 10 + [0] * 7
    res = mcnemar_exact(a, b, intervals=("exact", "bootstrap"))
    assert res["difference"] == pytest.approx(-0.15) and res["p_value"] == pytest.approx(0.25)
    assert res["difference_ci"][1] < 0  # the old interval: excludes 0
    lo, hi = res["difference_exact_ci"]
    assert lo == pytest.approx(-0.15) and 0 < hi  # 0 of 3: pi in [0, 1 - 0.025 ** (1 / 3)]
    assert hi == pytest.approx(3 / 20 * (2 * (1 - 0.025 ** (1 / 3)) - 1))


@pytest.mark.parametrize("n", [12, pytest.param(40, marks=pytest.mark.slow)])
def test_the_exact_interval_excludes_zero_exactly_when_the_test_rejects(n: int) -> None:
    for b10 in range(n + 1):
        for b01 in range(n + 1 - b10):
            p = mcnemar_exact(
                [1] * b10 + [0] * b01 + [1] * (n - b10 - b01), [0] * b10 + [1] * b01 + [1] * (n - b10 - b01)
            )
            lo, hi = mcnemar_difference_ci(b10, b01, n)
            assert (lo > 0 or hi < 0) == (p["p_value"] < 0.05), (b10, b01, lo, hi, p["p_value"])
            assert -1 <= lo <= p["difference"] <= hi <= 1


def test_paired_verdict_reads_the_adjusted_p_value() -> None:
    assert paired_verdict(0.1, 0.01) == "better"
    assert paired_verdict(-0.1, 0.049) == "worse"
    assert paired_verdict(-0.1, 0.051) == "no difference shown"
    assert paired_verdict(0.0, 0.0) == "no difference shown"
    assert paired_verdict(0.1, None) == "not tested"
    assert set(VERDICTS) == {"better", "worse", "no difference shown"}


def test_wilcoxon_hand_worked() -> None:
    # differences 1, 2, 3, -4, 5 -> ranks 1..5, W- = 4; exact two-sided p = 2 * #{subsets with sum <= 4} / 2**5
    # subsets of {1..5} with sum <= 4: {}, {1}, {2}, {3}, {4}, {1,2}, {1,3} = 7
    a = [11.0, 12.0, 13.0, 6.0, 15.0]
    b = [10.0] * 5
    res = wilcoxon_paired(a, b)
    assert res["n"] == 5 and res["n_nonzero"] == 5
    assert res["statistic"] == pytest.approx(4.0)
    assert res["p_value"] == pytest.approx(2 * 7 / 32)
    assert res["median_difference"] == pytest.approx(2.0)
    assert res["mean_difference"] == pytest.approx((1 + 2 + 3 - 4 + 5) / 5)


def test_wilcoxon_ties_differences_equal_in_exact_arithmetic() -> None:
    # times on the 0.4 s control grid: 14.4 - 14.0 and 2.8 - 2.4 are both 0.4, but not in float64
    assert 14.4 - 14.0 != 2.8 - 2.4
    a = [14.4, 2.8, 10.8, 5.2, 7.6]
    b = [14.0, 2.4, 10.0, 6.0, 7.6 + 1e-15]  # differences 0.4, 0.4, 0.8, -0.8, ~0
    res = wilcoxon_paired(a, b)
    assert res["n"] == 5 and res["n_nonzero"] == 4  # rounding noise is no difference
    exact = wilcoxon_paired([2.0, 2.0, 4.0, 1.0], [1.0, 1.0, 2.0, 3.0])  # the same differences x 2.5, exact ties
    assert res["statistic"] == pytest.approx(exact["statistic"]) and res["p_value"] == pytest.approx(exact["p_value"])


def test_wilcoxon_degenerate() -> None:
    none = wilcoxon_paired([], [])
    assert none["n"] == 0 and none["p_value"] == 1.0 and math.isnan(none["median_difference"])
    same = wilcoxon_paired([1.0, 2.0], [1.0, 2.0])
    assert same["n"] == 2 and same["p_value"] == 1.0 and same["median_difference"] == 0.0
    # a pair with nan is dropped, not an error
    assert wilcoxon_paired([1.0, math.nan], [0.0, 3.0])["n"] == 1
    with pytest.raises(ValueError, match="same length"):
        wilcoxon_paired([1.0], [1.0, 2.0])


def test_holm_hand_value() -> None:
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])
    assert holm([]) == []
    with pytest.raises(ValueError):
        holm([1.5])


def test_min_detectable_difference_has_the_stated_power() -> None:
    n, psi = 500, 0.1
    delta = mcnemar_min_detectable_difference(n, psi)
    z_a = sps.norm.ppf(0.975)
    power = sps.norm.cdf((math.sqrt(n) * delta - z_a * math.sqrt(psi)) / math.sqrt(psi - delta**2))
    assert power == pytest.approx(0.8, abs=1e-9)
    assert 0.03 < delta < 0.045  # about (1.96 + 0.84) * sqrt(0.1 / 500) = 0.0396, a bit less
    assert math.isnan(mcnemar_min_detectable_difference(500, 0.0))
    assert mcnemar_min_detectable_difference(1500, psi) < delta


def test_welch_seed_test_hand_value() -> None:
    # means 0.85 and 0.6; sample variances 0.005 and 0.01; se^2 = 0.005/2 + 0.01/3
    a, b = [0.80, 0.90], [0.5, 0.6, 0.7]
    res = welch_seed_test(a, b)
    se2 = 0.005 / 2 + 0.01 / 3
    df = se2**2 / ((0.005 / 2) ** 2 / 1 + (0.01 / 3) ** 2 / 2)
    assert res["difference"] == pytest.approx(0.25)
    assert res["statistic"] == pytest.approx(0.25 / math.sqrt(se2))
    assert res["df"] == pytest.approx(df) and res["df"] == pytest.approx(2.8824, abs=1e-3)
    ref = sps.ttest_ind(a, b, equal_var=False)  # scipy's own Welch test
    assert res["p_value"] == pytest.approx(ref.pvalue)
    lo, hi = res["difference_ci"]
    assert (lo + hi) / 2 == pytest.approx(0.25) and lo < 0.25 < hi


def test_welch_seed_test_fixed_side_and_degenerate_inputs() -> None:
    # one fixed value: a one-sample t-test of the other side against it
    res = welch_seed_test([0.7, 0.8, 0.9], [0.95])
    ref = sps.ttest_1samp([0.7, 0.8, 0.9], 0.95)
    assert res["df"] == pytest.approx(2.0) and res["p_value"] == pytest.approx(ref.pvalue)
    for a, b in (([0.5], [0.6]), ([0.5, 0.5], [0.5, 0.5])):
        res = welch_seed_test(a, b)
        assert math.isnan(res["p_value"]) and "no variance" in res["note"]
    assert "no seeds" in welch_seed_test([], [0.5])["note"]


def test_paired_seed_test_pairs_seed_i_with_seed_i() -> None:
    # the same rates paired differently: seed-by-seed differences (0.1, 0.1, 0.1, 0.2) are steady although the rates
    # vary widely between seeds, which an unpaired test would count against the difference
    a, b = [0.9, 0.7, 0.5, 0.8], [0.8, 0.6, 0.4, 0.6]
    res = paired_seed_test(a, b)
    ref = sps.ttest_rel(a, b)  # scipy's own paired test
    assert res["test"] == "paired t on per-seed rates" and res["df"] == pytest.approx(3.0)
    assert res["difference"] == pytest.approx(0.125) and res["p_value"] == pytest.approx(ref.pvalue)
    d = np.array(a) - np.array(b)
    half = sps.t.ppf(0.975, 3) * d.std(ddof=1) / 2
    assert res["difference_ci"] == pytest.approx([0.125 - half, 0.125 + half])
    assert res["p_value"] < welch_seed_test(a, b)["p_value"]
    # reversing b's seeds breaks the pairing and changes the test (Welch's would not change)
    assert paired_seed_test(a, b[::-1])["p_value"] != pytest.approx(res["p_value"])


def test_paired_seed_test_fixed_side_and_degenerate_inputs() -> None:
    res = paired_seed_test([0.7, 0.8, 0.9], [0.95])
    assert res["test"].startswith("one-sample") and res["p_value"] == pytest.approx(
        sps.ttest_1samp([0.7, 0.8, 0.9], 0.95).pvalue
    )
    assert paired_seed_test([0.95], [0.7, 0.8, 0.9])["difference"] == pytest.approx(0.15)
    with pytest.raises(ValueError, match="as many seeds"):
        paired_seed_test([0.5, 0.6, 0.7], [0.5, 0.6])
    for a, b in (([0.5], [0.6]), ([0.6, 0.7], [0.5, 0.6])):
        out = paired_seed_test(a, b)
        assert math.isnan(out["p_value"]) and "no variance" in out["note"]
    assert "no seeds" in paired_seed_test([], [0.5])["note"]


def test_paired_seed_test_differences_equal_in_exact_arithmetic() -> None:
    # per-seed rates over 500 episodes, every seed of a 9 episodes above its seed of b: identical differences, so
    # there is no variance to test from -- but 416/500 - 407/500 and 410/500 - 401/500 differ in the last bit, which
    # made t about 1e15 and p about 1e-59 (a "significant" seed-level test out of rounding noise)
    a = np.array([416, 410, 426, 491, 474]) / 500
    b = np.array([407, 401, 417, 482, 465]) / 500
    assert len(set((a - b).tolist())) > 1
    out = paired_seed_test(a, b)
    assert math.isnan(out["p_value"]) and "no variance" in out["note"]
    assert out["difference"] == pytest.approx(9 / 500) and all(math.isnan(v) for v in out["difference_ci"])
    # a real spread of the differences is still tested
    c = np.array([417, 410, 426, 491, 474]) / 500
    assert paired_seed_test(c, b)["p_value"] == pytest.approx(sps.ttest_rel(c, b).pvalue)
