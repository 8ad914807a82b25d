"""Statistics for evaluations and the ablation: intervals, paired tests, multiple-comparison correction.

Distributions and resampling come from scipy; the only formulas written here are the Holm step-down
rule, the sample-size relation of the McNemar power approximation and the linear map of a Clopper-Pearson
interval onto a difference of paired rates (each stated where defined).

Intervals agree with the tests beside them: the interval of a McNemar difference is the exact conditional one
(:func:`mcnemar_difference_ci`, 0 outside it exactly when the test rejects), and a comparison's plain verdict
(:func:`paired_verdict`) reads the multiplicity-adjusted p-value.

Conventions: every interval is a ``(lo, hi)`` tuple of floats (``nan`` when there is nothing to
estimate from); every test returns a JSON-serialisable dict; ``nan`` inputs (a metric that does not
apply to an episode, e.g. the forecast ADE of the ``none`` arm) are dropped — pairwise for paired
functions — and the number of values used is reported.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any, Final

import numpy as np
from scipy import optimize, stats

__all__ = [
    "DIFFERENCE_DECIMALS",
    "VERDICTS",
    "bootstrap_mean_ci",
    "holm",
    "mcnemar_difference_ci",
    "mcnemar_exact",
    "mcnemar_min_detectable_difference",
    "paired_bootstrap_diff_ci",
    "paired_seed_test",
    "paired_verdict",
    "welch_seed_test",
    "wilcoxon_paired",
    "wilson_interval",
]

NAN_CI: tuple[float, float] = (math.nan, math.nan)


def _check_confidence(confidence: float) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``successes / n`` (no continuity correction).

    ``n = 0`` gives ``(0.0, 1.0)``: nothing is known about the rate.
    """
    _check_confidence(confidence)
    successes, n = int(successes), int(n)
    if n < 0 or not 0 <= successes <= max(n, 0):
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return (0.0, 1.0)
    ci = stats.binomtest(successes, n).proportion_ci(confidence_level=confidence, method="wilson")
    return (float(ci.low), float(ci.high))


def _finite(values: Sequence[float] | np.ndarray) -> np.ndarray:
    x = np.asarray(values, dtype=float).ravel()
    return x[np.isfinite(x)]


def bootstrap_mean_ci(
    values: Sequence[float] | np.ndarray,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float]:
    """Bootstrap interval of the mean (``scipy.stats.bootstrap``, BCa; percentile when BCa is degenerate).

    Non-finite values are dropped. No values gives ``(nan, nan)``; one value or a constant array gives
    ``(v, v)`` (the resampling distribution is a point), without warnings.
    """
    _check_confidence(confidence)
    x = _finite(values)
    if x.size == 0:
        return NAN_CI
    if x.size == 1 or np.all(x == x[0]):
        return (float(x[0]), float(x[0]))
    for method in ("BCa", "percentile"):
        # BCa can be degenerate for nearly constant data (a warning and nan); the percentile method is not.
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", stats.DegenerateDataWarning)
            res = stats.bootstrap(
                (x,),
                np.mean,
                n_resamples=n_resamples,
                confidence_level=confidence,
                method=method,
                vectorized=True,
                rng=np.random.default_rng(seed),
            )
        lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
        if math.isfinite(lo) and math.isfinite(hi):
            return (lo, hi)
    return NAN_CI  # pragma: no cover - percentile intervals of finite data are finite


def _paired(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(a, dtype=float).ravel()
    y = np.asarray(b, dtype=float).ravel()
    if x.shape != y.shape:
        raise ValueError(f"paired samples need the same length, got {x.size} and {y.size}")
    keep = np.isfinite(x) & np.isfinite(y)
    return x[keep], y[keep]


def paired_bootstrap_diff_ci(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float]:
    """Bootstrap interval of ``mean(a - b)`` over pairs (pairs resampled together; non-finite pairs dropped)."""
    x, y = _paired(a, b)
    return bootstrap_mean_ci(x - y, confidence=confidence, n_resamples=n_resamples, seed=seed)


def mcnemar_difference_ci(b10: int, b01: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """The exact conditional interval of ``rate(a) - rate(b)`` that matches the exact McNemar test.

    Given ``m = b10 + b01`` discordant pairs out of ``n``, ``b10 ~ Binomial(m, pi)`` and the difference is
    ``(m / n) * (2 * pi - 1)``. The Clopper-Pearson interval ``[pi_lo, pi_hi]`` of ``pi``
    (``scipy.stats.binomtest(...).proportion_ci(method="exact")``) maps to ``[(m / n)(2 pi_lo - 1),
    (m / n)(2 pi_hi - 1)]``. Clopper-Pearson inverts the equal-tailed exact binomial test, which under
    ``pi = 1/2`` (a symmetric distribution) is the two-sided test :func:`mcnemar_exact` reports, so the interval
    excludes 0 exactly when ``p_value < 1 - confidence``. It is conditional on the discordant pairs observed, as
    the test is: it does not count how the number of discordant pairs itself could vary. No discordant pair gives
    ``(0.0, 0.0)``; ``n = 0`` gives ``(nan, nan)``.
    """
    _check_confidence(confidence)
    b10, b01, n = int(b10), int(b01), int(n)
    m = b10 + b01
    if b10 < 0 or b01 < 0 or m > n:
        raise ValueError(f"need 0 <= b10, b01 and b10 + b01 <= n, got b10={b10}, b01={b01}, n={n}")
    if n == 0:
        return NAN_CI
    if m == 0:
        return (0.0, 0.0)
    ci = stats.binomtest(b10, m, 0.5).proportion_ci(confidence_level=confidence, method="exact")
    scale = m / n
    return (float(scale * (2.0 * ci.low - 1.0)), float(scale * (2.0 * ci.high - 1.0)))


def mcnemar_exact(
    a_success: Sequence[bool] | np.ndarray,
    b_success: Sequence[bool] | np.ndarray,
    confidence: float = 0.95,
    seed: int = 0,
    intervals: Sequence[str] = ("exact",),
) -> dict[str, Any]:
    """Exact McNemar test of paired successes: a two-sided binomial test on the discordant pairs.

    ``b10`` counts pairs where ``a`` succeeded and ``b`` did not, ``b01`` the reverse; under the null
    hypothesis of equal success rates ``b10 ~ Binomial(b10 + b01, 1/2)``. No discordant pair gives
    ``p_value = 1``. ``difference`` is ``rate(a) - rate(b) = (b10 - b01) / n``.

    Args:
        intervals: which intervals of the difference to report: ``"exact"`` gives ``difference_exact_ci``
            (:func:`mcnemar_difference_ci`: excludes 0 exactly when ``p_value < 1 - confidence``);
            ``"bootstrap"`` gives ``difference_ci``, a paired bootstrap interval (the only interval before
            ``difference_exact_ci`` existed; it can exclude 0 beside a test that does not reject, so new reports
            use the exact one, and summaries written with it keep it).
    """
    unknown = set(intervals) - {"exact", "bootstrap"}
    if unknown:
        raise ValueError(f"unknown interval(s) {sorted(unknown)}; valid: exact, bootstrap")
    a = np.asarray(a_success).ravel()
    b = np.asarray(b_success).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired samples need the same length, got {a.size} and {b.size}")
    a, b = a.astype(bool), b.astype(bool)
    n = int(a.size)
    b10 = int(np.sum(a & ~b))
    b01 = int(np.sum(~a & b))
    discordant = b10 + b01
    p_value = 1.0 if discordant == 0 else float(stats.binomtest(b10, discordant, 0.5).pvalue)
    if n == 0:
        diff, ci = math.nan, NAN_CI
        rate_a = rate_b = math.nan
    else:
        diff = (b10 - b01) / n
        ci = NAN_CI
        if "bootstrap" in intervals:
            ci = paired_bootstrap_diff_ci(a.astype(float), b.astype(float), confidence=confidence, seed=seed)
        rate_a, rate_b = float(a.mean()), float(b.mean())
    out: dict[str, Any] = {
        "test": "exact McNemar",
        "n": n,
        "b01": b01,
        "b10": b10,
        "rate_a": rate_a,
        "rate_b": rate_b,
        "difference": diff,
    }
    if "bootstrap" in intervals:
        out["difference_ci"] = [ci[0], ci[1]]
    if "exact" in intervals:
        out["difference_exact_ci"] = list(mcnemar_difference_ci(b10, b01, n, confidence))
    out["p_value"] = min(p_value, 1.0)
    return out


#: The plain verdicts of a paired comparison ``a`` against ``b`` (:func:`paired_verdict`).
VERDICTS: tuple[str, ...] = ("better", "worse", "no difference shown")


def paired_verdict(difference: float | None, p_adjusted: float | None, alpha: float = 0.05) -> str:
    """``"better"`` (``a`` above ``b``) or ``"worse"`` when the multiplicity-adjusted p-value is at most ``alpha``,
    by the sign of ``difference`` (``a - b``, higher is better); else ``"no difference shown"`` -- which is not a
    finding of equality. ``"not tested"`` without a p-value."""
    if p_adjusted is None or difference is None or not math.isfinite(p_adjusted):
        return "not tested"
    if p_adjusted <= alpha and difference != 0:
        return VERDICTS[0] if difference > 0 else VERDICTS[1]
    return VERDICTS[2]


#: Decimals the paired differences are rounded to before the Wilcoxon signed-rank test ranks them
#: (:func:`wilcoxon_paired`): far below any difference the metrics resolve (seconds, metres, counts), far above
#: float64 rounding noise at their magnitudes.
DIFFERENCE_DECIMALS: Final[int] = 9


def wilcoxon_paired(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """Two-sided Wilcoxon signed-rank test of ``a - b`` (``scipy.stats.wilcoxon``, zero differences dropped).

    Pairs with a non-finite member are dropped first; ``n`` counts the pairs used, ``n_nonzero`` those with a
    non-zero difference. With no pair, or no non-zero difference, there is no evidence of a difference:
    ``statistic = 0.0`` and ``p_value = 1.0`` (``note`` says which case). ``median_difference`` and
    ``mean_difference`` are the median and mean of ``a - b`` over all used pairs (``nan`` without pairs;
    the mean shows a shift the median hides when times are quantised to control steps).

    The differences are rounded to :data:`DIFFERENCE_DECIMALS` decimals before ranking: values on a grid (times in
    control steps of 0.4 s) give differences that are equal in exact arithmetic but not in floating point
    (``14.4 - 14.0`` and ``2.8 - 2.4`` differ in the last bit), which would break their ties by rounding noise and
    count a difference of 1e-15 as non-zero.
    """
    x, y = _paired(a, b)
    d = np.round(x - y, DIFFERENCE_DECIMALS)
    n = int(d.size)
    nonzero = int(np.count_nonzero(d))
    out: dict[str, Any] = {
        "test": "Wilcoxon signed-rank",
        "n": n,
        "n_nonzero": nonzero,
        "median_difference": float(np.median(d)) if n else math.nan,
        "mean_difference": float(np.mean(d)) if n else math.nan,
    }
    if nonzero == 0:
        out.update(statistic=0.0, p_value=1.0, note="no pairs" if n == 0 else "all differences are zero")
        return out
    res = stats.wilcoxon(d, zero_method="wilcox", alternative="two-sided")
    out.update(statistic=float(res.statistic), p_value=float(res.pvalue))
    return out


def _untestable(out: dict[str, Any], note: str) -> dict[str, Any]:
    """``out`` of a seed-level test with nothing to test from: ``nan`` interval, p, df and statistic, and why."""
    out.update(difference_ci=[math.nan, math.nan], p_value=math.nan, df=math.nan, statistic=math.nan, note=note)
    return out


def welch_seed_test(
    a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray, confidence: float = 0.95
) -> dict[str, Any]:
    """Welch's t-test of ``mean(a) - mean(b)`` where each value is one training seed's rate.

    The unit is the training seed, so the interval counts the variance between independently trained
    policies that an episode-level test (McNemar over (seed, episode) pairs) leaves out. A side with a
    single value is a fixed quantity (e.g. a deterministic planner evaluated once): it adds no variance
    and no degrees of freedom, and the test becomes a one-sample t-test of the other side. Standard error
    ``se = sqrt(var_a / n_a + var_b / n_b)`` (sample variances, ``ddof = 1``; 0 for a single value);
    Welch-Satterthwaite degrees of freedom ``se**4 / sum((var_i / n_i)**2 / (n_i - 1))`` over the sides
    with ``n_i >= 2``; interval ``difference +- t_{df, (1 + confidence) / 2} * se``. Without any seed
    variance (fewer than two values on both sides, or identical values) there is nothing to test from:
    ``p_value`` and the interval are ``nan`` and ``note`` says why.
    """
    _check_confidence(confidence)
    x, y = _finite(a), _finite(b)
    out: dict[str, Any] = {"test": "Welch t on per-seed rates", "n_a": int(x.size), "n_b": int(y.size)}
    if x.size == 0 or y.size == 0:
        out.update(
            difference=math.nan,
            difference_ci=[math.nan, math.nan],
            p_value=math.nan,
            df=math.nan,
            note="a side has no seeds",
        )
        return out
    diff = float(x.mean() - y.mean())
    terms = [float(v.var(ddof=1)) / v.size for v in (x, y) if v.size >= 2]
    dofs = [v.size - 1 for v in (x, y) if v.size >= 2]
    se2 = sum(terms)
    out["difference"] = diff
    if se2 <= 0.0:
        return _untestable(out, "no variance between seeds (fewer than two seeds, or identical rates)")
    df = se2**2 / sum(t * t / d for t, d in zip(terms, dofs, strict=True))
    se = math.sqrt(se2)
    t = diff / se
    half = float(stats.t.ppf(0.5 + confidence / 2.0, df)) * se
    out.update(
        statistic=t,
        df=df,
        standard_error=se,
        difference_ci=[diff - half, diff + half],
        p_value=float(min(1.0, 2.0 * stats.t.sf(abs(t), df))),
    )
    return out


def paired_seed_test(
    a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray, confidence: float = 0.95
) -> dict[str, Any]:
    """The seed-level test of ``mean(a) - mean(b)`` where each value is one training seed's rate over the same
    episodes, paired by seed as declared: value ``i`` of ``a`` and of ``b`` come from training seed ``i``.

    With a value per seed on both sides: the paired t-test on the per-seed differences ``d_i = a_i - b_i``
    (``scipy.stats.ttest_1samp`` of ``d`` against 0; ``n - 1`` degrees of freedom; interval ``mean(d) +-
    t_{n-1} sd(d) / sqrt(n)``). With a single value on one side (a deterministic planner, evaluated once on the
    same episodes): the other side's per-seed rates minus that fixed rate, the same one-sample test. ``n_a``,
    ``n_b`` count the values; a pair with a non-finite value is dropped. Without two differences, or with identical
    ones (equal to :data:`DIFFERENCE_DECIMALS` decimals), there is nothing to test from: ``p_value`` and the interval
    are ``nan`` and ``note`` says why.

    Raises:
        ValueError: both sides have several values but not the same number (they cannot be paired by seed).
    """
    _check_confidence(confidence)
    x, y = np.asarray(a, dtype=float).ravel(), np.asarray(b, dtype=float).ravel()
    out: dict[str, Any] = {"n_a": int(x.size), "n_b": int(y.size)}
    if x.size > 1 and y.size > 1 and x.size != y.size:
        raise ValueError(f"paired by seed needs as many seeds on both sides, got {x.size} and {y.size}")
    if x.size == 0 or y.size == 0:
        out.update(test="paired t on per-seed rates", difference=math.nan, difference_ci=[math.nan, math.nan])
        out.update(p_value=math.nan, df=math.nan, note="a side has no seeds")
        return out
    fixed = x.size == 1 or y.size == 1
    out["test"] = "one-sample t of per-seed rates against the fixed rate" if fixed else "paired t on per-seed rates"
    d = x - y  # broadcasts a single value against the other side's seeds
    d = d[np.isfinite(d)]
    n = int(d.size)
    diff = float(d.mean()) if n else math.nan
    out["difference"] = diff
    # identical differences up to rounding noise: rates k / n of different seeds give differences equal in exact
    # arithmetic but not in float64 (416/500 - 407/500 != 410/500 - 401/500), whose spread of 1e-17 would make t
    # about 1e15 (as :func:`wilcoxon_paired` rounds before ranking)
    if n < 2 or float(np.ptp(np.round(d, DIFFERENCE_DECIMALS))) == 0.0:
        return _untestable(out, "no variance between seeds (fewer than two seeds, or identical differences)")
    res = stats.ttest_1samp(d, 0.0)
    se = float(d.std(ddof=1)) / math.sqrt(n)
    half = float(stats.t.ppf(0.5 + confidence / 2.0, n - 1)) * se
    out.update(
        statistic=float(res.statistic),
        df=float(n - 1),
        standard_error=se,
        difference_ci=[diff - half, diff + half],
        p_value=float(res.pvalue),
    )
    return out


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm–Bonferroni adjusted p-values, in the input order.

    Step-down rule: with the ``m`` p-values sorted ascending, ``p_(i)`` (``i = 1..m``) becomes
    ``max_{j <= i} min(1, (m - j + 1) * p_(j))``. Rejecting where the adjusted value is ``<= alpha``
    controls the family-wise error rate at ``alpha``.
    """
    p = np.asarray(pvalues, dtype=float).ravel()
    if np.any(~np.isfinite(p)) or np.any((p < 0) | (p > 1)):
        raise ValueError(f"p-values must lie in [0, 1], got {list(p)}")
    m = p.size
    order = np.argsort(p, kind="stable")
    stepped = np.minimum(1.0, (m - np.arange(m)) * p[order])
    adjusted = np.empty(m)
    adjusted[order] = np.maximum.accumulate(stepped)
    return [float(v) for v in adjusted]


def mcnemar_min_detectable_difference(
    n: int, discordant_fraction: float, alpha: float = 0.05, power: float = 0.8
) -> float:
    """Smallest ``|rate(a) - rate(b)|`` a two-sided McNemar test detects with the given power.

    Normal approximation of Connor (1987): ``n`` pairs with discordant fraction ``psi`` detect a
    difference ``delta`` when ``sqrt(n) * delta = z_{1-alpha/2} * sqrt(psi) + z_{power} * sqrt(psi - delta**2)``;
    solved for ``delta`` in ``(0, psi]``. ``nan`` when ``n = 0`` or ``psi = 0`` (no discordance observed,
    nothing to plan from). ``psi`` is taken as observed, i.e. assumed to stay the same under the alternative.
    """
    if not 0.0 < alpha < 1.0 or not 0.0 < power < 1.0:
        raise ValueError(f"alpha and power must lie in (0, 1), got alpha={alpha!r}, power={power!r}")
    psi = float(discordant_fraction)
    if n <= 0 or psi <= 0.0:
        return math.nan
    if psi > 1.0:
        raise ValueError(f"discordant_fraction must lie in [0, 1], got {psi!r}")
    z_a = float(stats.norm.ppf(1.0 - alpha / 2.0))
    z_b = float(stats.norm.ppf(power))

    def gap(delta: float) -> float:
        return math.sqrt(n) * delta - z_a * math.sqrt(psi) - z_b * math.sqrt(max(psi - delta * delta, 0.0))

    hi = min(psi, 1.0)
    if gap(hi) < 0.0:
        return math.nan  # even the largest difference the discordance allows is not detectable
    return float(optimize.brentq(gap, 0.0, hi))
