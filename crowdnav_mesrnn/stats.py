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

Comparisons over training seeds (:func:`seeded_bootstrap_ci`) add a second level: a replicate draws
the blocks of windows (shared by both models: the comparison stays paired) and, independently for each
model, as many seeds as it has, with replacement; the statistic is the difference of the two models'
seed-averaged errors. The interval then covers how much the difference depends on which seeds were
trained as well as on which windows were recorded. With few seeds (three in the plan) resampling seeds
understates their variance by a factor ``(S − 1) / S``, so such an interval is still optimistic.

Randomness comes from :class:`numpy.random.Generator` only; intervals are percentile intervals.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

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


def _seeded_replicates(
    a: SeededErrors, b: SeededErrors, block_len: int, n_resamples: int, rng: np.random.Generator
) -> np.ndarray:
    starts = _block_starts(len(a.count), block_len, n_resamples, rng)
    count = _block_totals(a.count[None], starts, block_len)[0]
    cols = np.arange(n_resamples)[:, None]
    means = []
    for e in (a, b):
        totals = _block_totals(e.sums, starts, block_len)  # (S, n)
        draws = rng.integers(0, e.seeds, size=(n_resamples, e.seeds))
        means.append(totals.T[cols, draws].mean(1))
    return (means[0] - means[1]) / count


def seeded_bootstrap_replicates(
    a: SeededErrors,
    b: SeededErrors,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> np.ndarray:
    """``(n_resamples,)`` two-level bootstrap replicates of ``A − B`` (seed-averaged): blocks of windows
    shared by both, seeds drawn with replacement for each model separately. With one seed each, the
    replicates are exactly :func:`block_bootstrap_replicates` of the paired difference."""
    _check(block_len, n_resamples, 0.5)
    _check_pair(a, b)
    return _seeded_replicates(a, b, block_len, n_resamples, np.random.default_rng(seed))


def seeded_bootstrap_ci(
    a: SeededErrors,
    b: SeededErrors,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, tuple[float, float]]:
    """The seed-averaged difference ``A − B`` on one split and its two-level percentile interval."""
    _check(block_len, n_resamples, confidence)
    reps = seeded_bootstrap_replicates(a, b, block_len, n_resamples, seed)
    return a.estimate - b.estimate, _percentile_interval(reps, confidence)


def seeded_average_ci(
    pairs: Sequence[tuple[SeededErrors, SeededErrors]],
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, tuple[float, float]]:
    """The unweighted mean over splits of the seed-averaged differences, and its interval (each split's
    windows and seeds resampled independently: each split's models were trained separately)."""
    _check(block_len, n_resamples, confidence)
    if not pairs:
        raise ValueError("need at least one split")
    for a, b in pairs:
        _check_pair(a, b)
    rngs = np.random.default_rng(seed).spawn(len(pairs))
    reps = np.mean(
        [_seeded_replicates(a, b, block_len, n_resamples, r) for (a, b), r in zip(pairs, rngs, strict=True)], axis=0
    )
    estimate = float(np.mean([a.estimate - b.estimate for a, b in pairs]))
    return estimate, _percentile_interval(reps, confidence)


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
