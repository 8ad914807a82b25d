"""Block bootstrap intervals for paired ADE/FDE differences between predictors.

Test windows slide by one annotation step over each recording, so consecutive windows share up to
19 of their 20 frames (and mostly the same pedestrians): their errors are strongly correlated and
resampling single windows would give intervals that are too narrow. The moving-block bootstrap
(Künsch 1989) resamples blocks of ``block_len`` consecutive windows instead. The default block
length is 20 windows, the length of one window in annotation steps: windows 20 or more steps apart
share no frame. It is a parameter (``--block-len`` on the command line), and a block length of 1 is
the ordinary bootstrap.

A split's ADE is pedestrian-weighted (the mean over every scored pedestrian of every window), so the
statistic of a resample is the ratio ``Σ errors / Σ pedestrians`` over the resampled windows, not
the mean of per-window means. The five-split average is the unweighted mean of the five split
figures (as on the results page); its interval resamples each split independently (the five test
sets are different recordings) and averages the five resampled statistics.

Comparisons over training seeds (:func:`seeded_difference_ci`) add the seeds' variance. Resampling
three seeds with replacement would be far too optimistic (a percentile interval of a mean of three
seeds cannot reach beyond them: about 75 % coverage where 95 % is claimed), so the two sources are
combined in a t interval instead: the window part is the variance of the block-bootstrap replicates of
the seed-averaged difference; the seed part is ``s_A² / S_A + s_B² / S_B``, the sample variances of
each model's per-seed errors; the degrees of freedom are Welch-Satterthwaite's, with the window part
counted as known exactly. Three seeds against constant velocity have 2 degrees of freedom (t = 4.30).
The five-split average takes each seed's average over the splits (seed ``k`` of every split together),
so seed effects shared across splits are counted. With one seed each this is the block bootstrap above.

Randomness comes from :class:`numpy.random.Generator` only; intervals are percentile intervals, except
the t intervals over seeds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as sps

#: Default block length in windows: one window spans 20 annotation steps.
DEFAULT_BLOCK_LEN = 20
DEFAULT_RESAMPLES = 10_000


@dataclass(frozen=True)
class PairedErrors:
    """Per-window sums of a paired error difference ``A − B`` on one split, windows in time order.

    Attributes:
        diff_sum: ``(W,)`` Σ over the window's scored pedestrians of ``error_A − error_B`` (metres).
        count: ``(W,)`` number of scored pedestrians in each window (> 0).
    """

    diff_sum: np.ndarray
    count: np.ndarray

    def __post_init__(self) -> None:
        d = np.asarray(self.diff_sum, dtype=float)
        c = np.asarray(self.count, dtype=float)
        if d.ndim != 1 or d.shape != c.shape or len(d) == 0:
            raise ValueError(f"diff_sum and count must be equal-length non-empty 1-D arrays, got {d.shape}, {c.shape}")
        _check_windows(d, c)
        object.__setattr__(self, "diff_sum", d)
        object.__setattr__(self, "count", c)

    @property
    def estimate(self) -> float:
        """The pedestrian-weighted mean difference (what the results page reports)."""
        return float(self.diff_sum.sum() / self.count.sum())


def _check_windows(values: np.ndarray, count: np.ndarray) -> None:
    if np.any(count <= 0) or not np.all(np.isfinite(values)):
        raise ValueError("every window needs a positive pedestrian count and finite errors")


def _check(block_len: int, n_resamples: int, confidence: float) -> None:
    if block_len < 1:
        raise ValueError(f"block_len must be >= 1, got {block_len}")
    if n_resamples < 1:
        raise ValueError(f"n_resamples must be >= 1, got {n_resamples}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")


def block_bootstrap_replicates(
    errors: PairedErrors, block_len: int = DEFAULT_BLOCK_LEN, n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0
) -> np.ndarray:
    """``(n_resamples,)`` moving-block bootstrap replicates of :attr:`PairedErrors.estimate`.

    Each replicate concatenates ``ceil(W / L)`` blocks of ``L = min(block_len, W)`` consecutive windows,
    with starts drawn uniformly from ``0 .. W − L``, and keeps the first ``W`` windows.
    """
    _check(block_len, n_resamples, 0.5)
    return _replicates(errors, block_len, n_resamples, np.random.default_rng(seed))


def _replicates(errors: PairedErrors, block_len: int, n_resamples: int, rng: np.random.Generator) -> np.ndarray:
    starts = _block_starts(len(errors.diff_sum), block_len, n_resamples, rng)
    totals = _block_totals(np.stack([errors.diff_sum, errors.count]), starts, block_len)
    return totals[0] / totals[1]


def _block_starts(w: int, block_len: int, n_resamples: int, rng: np.random.Generator) -> np.ndarray:
    """``(n_resamples, ceil(W / L))`` block starts drawn uniformly from ``0 .. W − L``, ``L = min(block_len, W)``."""
    length = min(block_len, w)
    return rng.integers(0, w - length + 1, size=(n_resamples, math.ceil(w / length)))


def _block_totals(values: np.ndarray, starts: np.ndarray, block_len: int) -> np.ndarray:
    """``(K, n_resamples)`` sums of each row of ``values`` ``(K, W)`` over the resampled windows: the
    blocks at ``starts``, cut to ``W`` windows (windows of the last block beyond ``W`` are dropped)."""
    w = values.shape[1]
    length = min(block_len, w)
    # Prefix sums turn each block's sums into two look-ups.
    cum = np.concatenate([np.zeros((len(values), 1)), np.cumsum(values, axis=1)], axis=1)
    out = (cum[:, starts + length] - cum[:, starts]).sum(-1)
    tail = starts.shape[1] * length - w
    if tail:
        last = starts[:, -1] + length
        out -= cum[:, last] - cum[:, last - tail]
    return out


def block_totals_replicates(
    values: np.ndarray, block_len: int, n_resamples: int, rng: np.random.Generator
) -> np.ndarray:
    """``(K, n_resamples)`` moving-block bootstrap replicates of the totals of each row of ``values``
    ``(K, W)`` (windows in time order), all rows resampled with the same blocks (as
    :func:`block_bootstrap_replicates`, whose statistic is the ratio of two such rows)."""
    _check(block_len, n_resamples, 0.5)
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or values.shape[1] == 0:
        raise ValueError(f"values must be (rows, windows) with at least one window, got {values.shape}")
    return _block_totals(values, _block_starts(values.shape[1], block_len, n_resamples, rng), block_len)


def _percentile_interval(replicates: np.ndarray, confidence: float) -> tuple[float, float]:
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(replicates, [alpha, 1.0 - alpha])
    return float(lo), float(hi)


def block_bootstrap_ci(
    errors: PairedErrors,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile interval of the pedestrian-weighted mean difference on one split."""
    _check(block_len, n_resamples, confidence)
    return _percentile_interval(block_bootstrap_replicates(errors, block_len, n_resamples, seed), confidence)


def average_ci(
    per_split: Mapping[str, PairedErrors] | Sequence[PairedErrors],
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, tuple[float, float]]:
    """The unweighted mean over splits of their differences, and its interval (each split resampled
    independently with its own stream of ``seed``)."""
    _check(block_len, n_resamples, confidence)
    items = list(per_split.values()) if isinstance(per_split, Mapping) else list(per_split)
    if not items:
        raise ValueError("need at least one split")
    rngs = np.random.default_rng(seed).spawn(len(items))
    reps = np.mean([_replicates(e, block_len, n_resamples, r) for e, r in zip(items, rngs, strict=True)], axis=0)
    estimate = float(np.mean([e.estimate for e in items]))
    return estimate, _percentile_interval(reps, confidence)


@dataclass(frozen=True)
class SeededErrors:
    """Per-window error sums of one model on one split for each of its training seeds.

    Attributes:
        sums: ``(S, W)`` Σ over the window's scored pedestrians of the error (metres), one row per seed
            (a deterministic model such as constant velocity has one row).
        count: ``(W,)`` number of scored pedestrians in each window (> 0), the same for every seed.
    """

    sums: np.ndarray
    count: np.ndarray

    def __post_init__(self) -> None:
        x = np.atleast_2d(np.asarray(self.sums, dtype=float))
        c = np.asarray(self.count, dtype=float)
        if x.ndim != 2 or c.ndim != 1 or x.shape[1] != len(c) or x.size == 0:
            raise ValueError(f"sums must be (seeds, windows) and count (windows,), got {x.shape}, {c.shape}")
        _check_windows(x, c)
        object.__setattr__(self, "sums", x)
        object.__setattr__(self, "count", c)

    @property
    def seeds(self) -> int:
        return len(self.sums)

    @property
    def estimate(self) -> float:
        """The pedestrian-weighted error averaged over seeds."""
        return float(self.sums.mean(0).sum() / self.count.sum())


def _check_pair(a: SeededErrors, b: SeededErrors) -> None:
    if not np.array_equal(a.count, b.count):
        raise ValueError("the two models were scored on different windows or pedestrians")


@dataclass(frozen=True)
class SeededDifference:
    """A seed-averaged difference ``A − B`` and its interval (:func:`seeded_difference_ci`)."""

    estimate: float
    interval: tuple[float, float]
    window_se: float
    """Standard error from the test windows (block bootstrap of the seed-averaged difference)."""
    seed_se: float
    """Standard error from the training seeds, ``sqrt(s_A² / S_A + s_B² / S_B)`` (0 with one seed each)."""
    df: float
    """Welch-Satterthwaite degrees of freedom of the t quantile (``inf``: a percentile interval)."""


def _seed_means(e: SeededErrors) -> np.ndarray:
    """Each seed's pedestrian-weighted error on the whole split."""
    return e.sums.sum(1) / e.count.sum()


def combine_interval(
    estimate: float, replicates: np.ndarray, seed_means: Sequence[np.ndarray], confidence: float = 0.95
) -> SeededDifference:
    """A t interval whose variance adds the window replicates' variance and each side's ``s² / S``; with
    one seed on every side, the percentile interval of the replicates (the plain block bootstrap).

    Args:
        estimate: the seed-averaged difference ``A − B``.
        replicates: ``(R,)`` block-bootstrap replicates of it (finite).
        seed_means: per side, ``(S,)`` the statistic of each of its seeds on the whole data.
    """
    if all(len(m) == 1 for m in seed_means):
        return SeededDifference(
            estimate, _percentile_interval(replicates, confidence), float(np.std(replicates, ddof=1)), 0.0, math.inf
        )
    window_var = float(np.var(replicates, ddof=1)) if len(replicates) > 1 else 0.0
    terms = [(float(np.var(m, ddof=1)) / len(m), len(m) - 1) for m in seed_means if len(m) > 1]
    seed_var = sum(v for v, _ in terms)
    total = window_var + seed_var
    den = sum(v * v / k for v, k in terms)
    df = total * total / den if den > 0 else math.inf
    q = float(sps.t.ppf(0.5 + confidence / 2, df)) if math.isfinite(df) else float(sps.norm.ppf(0.5 + confidence / 2))
    half = q * math.sqrt(total)
    return SeededDifference(
        estimate, (estimate - half, estimate + half), math.sqrt(window_var), math.sqrt(seed_var), df
    )


def seeded_difference_ci(
    a: SeededErrors,
    b: SeededErrors,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> SeededDifference:
    """The seed-averaged difference ``A − B`` on one split, with an interval over windows and seeds
    (module docstring). With one seed each: exactly :func:`block_bootstrap_ci` of the paired difference.
    A model with one seed contributes no seed variance (right for constant velocity, which has none)."""
    _check(block_len, n_resamples, confidence)
    _check_pair(a, b)
    paired = PairedErrors(a.sums.mean(0) - b.sums.mean(0), a.count)
    reps = block_bootstrap_replicates(paired, block_len, n_resamples, seed)
    return combine_interval(paired.estimate, reps, [_seed_means(a), _seed_means(b)], confidence)


def seeded_average_ci(
    pairs: Sequence[tuple[SeededErrors, SeededErrors]],
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> SeededDifference:
    """The unweighted mean over splits of the seed-averaged differences, with an interval: each split's
    windows resampled independently (as :func:`average_ci`), and the seed part from each seed's average
    over the splits, so each model needs the same number of seeds, in the same order, on every split.
    With one seed each: exactly :func:`average_ci`."""
    _check(block_len, n_resamples, confidence)
    if not pairs:
        raise ValueError("need at least one split")
    for a, b in pairs:
        _check_pair(a, b)
    for side in (0, 1):
        if len({p[side].seeds for p in pairs}) != 1:
            raise ValueError("a model needs the same seeds on every split for a five-split average")
    paired = [PairedErrors(a.sums.mean(0) - b.sums.mean(0), a.count) for a, b in pairs]
    rngs = np.random.default_rng(seed).spawn(len(pairs))
    reps = np.mean([_replicates(e, block_len, n_resamples, r) for e, r in zip(paired, rngs, strict=True)], axis=0)
    estimate = float(np.mean([e.estimate for e in paired]))
    seed_means = [np.mean([_seed_means(p[side]) for p in pairs], axis=0) for side in (0, 1)]
    return combine_interval(estimate, reps, seed_means, confidence)


def verdict(interval: tuple[float, float], lower_is_better: bool = True) -> str:
    """Plain reading of an interval of ``A − B``: ``"A better"``, ``"B better"`` or
    ``"no detectable difference"`` (the interval includes 0)."""
    lo, hi = interval
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "not computed"
    if lo <= 0.0 <= hi:
        return "no detectable difference"
    a_lower = hi < 0.0
    return "A better" if a_lower == lower_is_better else "B better"


def ratio_differences(
    a_num: Sequence[np.ndarray],
    b_num: Sequence[np.ndarray] | None,
    den: Sequence[np.ndarray],
    contrasts: Sequence[tuple[int, int]] = (),
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> list[tuple[SeededDifference, float]]:
    """Differences ``A − B`` of ratio statistics per category (e.g. a density bin or a motion type),
    pooled over one or more splits, with block-bootstrap intervals (over windows and, with several seeds,
    seeds: :func:`combine_interval`).

    The statistic of category ``c`` is ``Σ_splits Σ_windows num[c] / Σ_splits Σ_windows den[c]`` (e.g. the
    pedestrian-weighted ADE of the pedestrians in that category, or the share of colliding pairs), each
    side's numerator averaged over its seeds. Every split's windows are resampled in blocks independently
    (its own stream of ``seed``) and the resampled totals added; every category is read from the same
    resample, so a contrast ``(hi, lo)`` — the statistic of category ``hi`` minus that of ``lo`` — gets its
    interval from the same replicates. A replicate in which a category has no weight is dropped for it;
    the share of dropped replicates is returned beside each result (an interval from very few windows of
    that category is not to be trusted: the caller decides from that share).

    Args:
        a_num: per split, ``(S_A, C, W)`` numerators of A, one row per seed, windows in time order.
        b_num: the same for B (``S_B`` may differ), or None for zero (the statistic of A itself).
        den: per split, ``(C, W)`` the weights (pedestrians, pairs), identical for both sides.
        contrasts: ``(hi, lo)`` category pairs, each appended to the result after the ``C`` categories.

    Returns:
        ``C + len(contrasts)`` pairs ``(difference, share of replicates dropped)``; a category with no
        weight at all has a nan estimate and interval.
    """
    _check(block_len, n_resamples, confidence)
    if not den or len(a_num) != len(den) or (b_num is not None and len(b_num) != len(den)):
        raise ValueError("need the same non-zero number of splits for a_num, b_num and den")
    a = [np.asarray(x, float) for x in a_num]
    b = [np.zeros((1, *np.shape(d))) for d in den] if b_num is None else [np.asarray(x, float) for x in b_num]
    dens = [np.asarray(d, float) for d in den]
    c = dens[0].shape[0]
    for x, y, d in zip(a, b, dens, strict=True):
        if x.ndim != 3 or y.ndim != 3 or d.ndim != 2 or x.shape[1:] != d.shape or y.shape[1:] != d.shape:
            raise ValueError(
                f"a split needs (S, C, W) numerators and (C, W) weights, got {x.shape}, {y.shape}, {d.shape}"
            )
        if d.shape[0] != c:
            raise ValueError("every split needs the same categories")
        _check_windows(x, np.ones(d.shape[1]))
    for side in (a, b):
        if len({x.shape[0] for x in side}) != 1:
            raise ValueError("a model needs the same seeds on every split")
    rngs = np.random.default_rng(seed).spawn(len(dens))
    totals = np.zeros((2 * c, n_resamples))
    for x, y, d, rng in zip(a, b, dens, rngs, strict=True):
        totals += block_totals_replicates(np.concatenate([x.mean(0) - y.mean(0), d]), block_len, n_resamples, rng)
    weight = sum(d.sum(1) for d in dens)
    with np.errstate(invalid="ignore", divide="ignore"):
        reps = totals[:c] / totals[c:]  # (C, R)
        est = sum((x.mean(0) - y.mean(0)).sum(1) for x, y in zip(a, b, strict=True)) / weight
        seeds = [sum(x.sum(-1) for x in side) / weight for side in (a, b)]  # (S, C) each seed's statistic
    rows = [(est[i], reps[i], [s[:, i] for s in seeds]) for i in range(c)]
    rows += [(est[h] - est[lo], reps[h] - reps[lo], [s[:, h] - s[:, lo] for s in seeds]) for h, lo in contrasts]
    out = []
    for estimate, r, per_seed in rows:
        finite = np.isfinite(r)
        if not np.isfinite(estimate) or not finite.any():
            nan = float("nan")
            out.append((SeededDifference(nan, (nan, nan), nan, nan, nan), 1.0))
            continue
        out.append((combine_interval(float(estimate), r[finite], per_seed, confidence), 1.0 - float(finite.mean())))
    return out
