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
        if np.any(c <= 0) or not np.all(np.isfinite(d)):
            raise ValueError("every window needs a positive pedestrian count and a finite difference")
        object.__setattr__(self, "diff_sum", d)
        object.__setattr__(self, "count", c)

    @property
    def estimate(self) -> float:
        """The pedestrian-weighted mean difference (what the results page reports)."""
        return float(self.diff_sum.sum() / self.count.sum())


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
    w = len(errors.diff_sum)
    length = min(block_len, w)
    n_blocks = math.ceil(w / length)
    # Prefix sums turn each block's sums into two look-ups.
    cd = np.concatenate([[0.0], np.cumsum(errors.diff_sum)])
    cc = np.concatenate([[0.0], np.cumsum(errors.count)])
    starts = rng.integers(0, w - length + 1, size=(n_resamples, n_blocks))
    d = (cd[starts + length] - cd[starts]).sum(1)
    c = (cc[starts + length] - cc[starts]).sum(1)
    tail = n_blocks * length - w  # windows of the last block beyond W are dropped
    if tail:
        last = starts[:, -1] + length
        d -= cd[last] - cd[last - tail]
        c -= cc[last] - cc[last - tail]
    return d / c


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
