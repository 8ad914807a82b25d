"""Conformal regions around forecasts: scores, split-conformal thresholds, calibrations and their coverage.

Every forecast step of every pedestrian gets a region ``{y : score(y) ≤ q_h(c)}`` meant to hold the true
position with probability ``c`` (levels 0.5, 0.9, 0.95). Two scores:

- ``scaled`` (the default): the Mahalanobis distance ``d`` of the true position under the forecast's Gaussian
  at that step, so the region is the Gaussian's own ellipse scaled by ``q_h(c)`` (the model's region is
  ``d ≤ sqrt(χ²₂(c))``; conformal calibration replaces that radius by ``q_h(c)``). A model with the distribution
  head (``head: gaussian``) supplies its Gaussians. A point forecast (constant velocity, point weights)
  gets an **error model** fitted on the split's training windows: an isotropic Gaussian whose scale grows with
  the pedestrian's last observed displacement, ``σ_h(v) = a_h + b_h v`` (``v`` in metres per annotation
  step, ``a_h, b_h ≥ 0`` by non-negative least squares of the errors' lengths, whose mean is ``σ sqrt(π/2)``
  for an isotropic Gaussian). The regions then widen with speed, horizon and the recording's step time.
- ``radius``: the error's length; the region is a disc of radius ``q_h(c)`` metres, the same for everyone.

Split conformal: per horizon step ``h``, ``q_h(c)`` is the ``⌈(n + 1) c⌉``-th smallest of the ``n`` calibration
scores (infinite when that exceeds ``n``); it would guarantee coverage ``≥ c`` if the scored pedestrians were
exchangeable with the calibration ones. These are the primitives both :mod:`crowdnav_mesrnn.uncertainty.calibration`
(split conformal) and :mod:`crowdnav_mesrnn.uncertainty.online_conformal` (thresholds tracked over a scene) build on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from scipy.optimize import nnls

from crowdnav_mesrnn.evaluation.metrics import ScoredForecasts
from crowdnav_mesrnn.evaluation.statistics import PairedErrors
from crowdnav_mesrnn.models import gaussian

#: Coverage levels of the regions.
LEVELS: Final[tuple[float, ...]] = (0.5, 0.9, 0.95)
#: Conformal scores (module docstring).
SCORES: Final[tuple[str, ...]] = ("scaled", "radius")
#: Smallest scale of the error model, metres (a standing pedestrian's forecast is still uncertain).
SIGMA_FLOOR_M: Final[float] = 0.01
#: Format of :meth:`Calibration.to_dict` (bump when its meaning changes; cached calibrations are then rebuilt).
CALIBRATION_FORMAT: Final[int] = 1


def level_key(level: float) -> str:
    """The JSON key of a level: ``"0.5"``, ``"0.9"``, ``"0.95"``."""
    return f"{level:g}"


@dataclass(frozen=True)
class ErrorModel:
    """An isotropic Gaussian around a point forecast: at horizon step ``h``, ``σ_h(v) = a_h + b_h v`` metres
    (floored at :data:`SIGMA_FLOOR_M`), ``v`` the pedestrian's last observed displacement in metres per
    annotation step.

    Attributes:
        a_m: ``(P,)`` scale at rest per step, metres.
        b: ``(P,)`` growth of the scale per metre of last displacement, per step.
    """

    a_m: tuple[float, ...]
    b: tuple[float, ...]

    @classmethod
    def fit(cls, scored: ScoredForecasts) -> ErrorModel:
        """Fit on point-forecast errors (training windows): per step, non-negative least squares of the error's
        length on ``sqrt(π/2) (1, v)`` (the mean length of an isotropic Gaussian error is ``σ sqrt(π/2)``)."""
        if len(scored.speed) < 2:
            raise ValueError("fitting an error model needs the errors of at least two pedestrians")
        length = np.linalg.norm(scored.error, axis=-1)  # (M, P)
        design = math.sqrt(math.pi / 2) * np.stack([np.ones_like(scored.speed), scored.speed], axis=1)
        a, b = [], []
        for h in range(length.shape[1]):
            coef, _ = nnls(design, length[:, h])
            a.append(float(coef[0]))
            b.append(float(coef[1]))
        return cls(tuple(a), tuple(b))

    def sigma(self, speed: np.ndarray) -> np.ndarray:
        """``(M, P)`` scales in metres for last displacements ``speed (M,)`` (metres per annotation step)."""
        s = np.asarray(self.a_m)[None, :] + np.asarray(self.b)[None, :] * np.asarray(speed, dtype=np.float64)[:, None]
        return np.maximum(s, SIGMA_FLOOR_M)

    def to_dict(self) -> dict[str, list[float]]:
        return {"a_m": list(self.a_m), "b": list(self.b)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ErrorModel:
        return cls(tuple(map(float, d["a_m"])), tuple(map(float, d["b"])))


def gaussians_of(scored: ScoredForecasts, error_model: ErrorModel | None) -> tuple[np.ndarray, np.ndarray]:
    """``(sigma (M, P, 2), rho (M, P))`` of the forecasts: their own (distribution head), else the error model's."""
    if scored.sigma is not None and scored.rho is not None:
        return scored.sigma, scored.rho
    if error_model is None:
        raise ValueError("point forecasts need an error model for a scaled score")
    s = error_model.sigma(scored.speed)
    return np.repeat(s[..., None], 2, axis=-1), np.zeros_like(s)


def region_scores(scored: ScoredForecasts, score: str, error_model: ErrorModel | None = None) -> np.ndarray:
    """``(M, P)`` conformal scores: the Mahalanobis distance (``scaled``) or the error's length in metres (``radius``)."""
    if score == "radius":
        return np.linalg.norm(scored.error, axis=-1)
    if score != "scaled":
        raise ValueError(f"unknown score {score!r}; valid: {', '.join(SCORES)}")
    sigma, rho = gaussians_of(scored, error_model)
    return np.sqrt(gaussian.squared_mahalanobis(scored.error, sigma, rho))


def conformal_quantile(scores: np.ndarray, level: float) -> float:
    """The split-conformal threshold: the ``⌈(n + 1) level⌉``-th smallest of ``n`` scores (``inf`` beyond ``n``)."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    n = len(scores)
    if not 0.0 < level < 1.0:
        raise ValueError(f"coverage level must lie in (0, 1), got {level!r}")
    k = math.ceil((n + 1) * level)
    if n == 0 or k > n:
        return math.inf
    return float(np.partition(scores, k - 1)[k - 1])


@dataclass(frozen=True)
class Calibration:
    """Conformal thresholds of one predictor on one split (fitted on its training and validation windows).

    Attributes:
        model: predictor name (``cv``, ``mesrnn``, ...).
        head: ``point`` or ``gaussian`` (``point`` for constant velocity).
        split: the leave-one-out split.
        score: ``scaled`` or ``radius``.
        thresholds: level key (:func:`level_key`) -> ``(P,)`` per-step threshold ``q_h`` (a Mahalanobis radius
            for ``scaled``, metres for ``radius``).
        error_model: the point forecast's error model (``scaled`` without a distribution head), else None.
        windows: validation windows the thresholds come from.
        pedestrians: validation pedestrians (scores per step).
    """

    model: str
    head: str
    split: str
    score: str
    thresholds: dict[str, tuple[float, ...]]
    error_model: ErrorModel | None
    windows: int
    pedestrians: int

    def threshold(self, level: float) -> np.ndarray:
        key = level_key(level)
        if key not in self.thresholds:
            raise ValueError(f"level {level!r} was not calibrated; calibrated: {', '.join(self.thresholds)}")
        return np.asarray(self.thresholds[key], dtype=np.float64)

    def radius_m(
        self, level: float, speed: np.ndarray, sigma: np.ndarray | None = None, rho: np.ndarray | None = None
    ) -> np.ndarray:
        """``(M, P)`` radius in metres of the smallest disc around each forecast step holding its ``level`` region:
        ``q_h`` (``radius``), or ``q_h`` times the Gaussian's major semi-axis (``scaled``; the Gaussian is the
        forecast's own, ``sigma (M, P, 2)`` and ``rho (M, P)``, else the error model's at ``speed (M,)``)."""
        q = self.threshold(level)[None, :]
        if self.score == "radius":
            return np.broadcast_to(q, (len(speed), len(q[0]))).copy()
        return q * self.unit_m(speed, sigma, rho)

    def unit_m(self, speed: np.ndarray, sigma: np.ndarray | None = None, rho: np.ndarray | None = None) -> np.ndarray:
        """``(M, P)`` metres the radius grows by per unit of threshold (:meth:`radius_m` is the threshold times it): 1 for
        ``radius``; for ``scaled`` the Gaussian's major semi-axis (the forecast's own, ``sigma (M, P, 2)`` and
        ``rho (M, P)``, else the error model's at ``speed (M,)``)."""
        if self.score == "radius":
            return np.ones((len(speed), len(next(iter(self.thresholds.values())))))
        if sigma is None or rho is None:
            if self.error_model is None:
                raise ValueError(f"the {self.model} calibration needs the forecasts' own Gaussians (sigma, rho)")
            return self.error_model.sigma(speed)
        return gaussian.major_semi_axis(np.asarray(sigma, np.float64), np.asarray(rho, np.float64))

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": CALIBRATION_FORMAT,
            "model": self.model,
            "head": self.head,
            "split": self.split,
            "score": self.score,
            "thresholds": {k: list(v) for k, v in self.thresholds.items()},
            "error_model": None if self.error_model is None else self.error_model.to_dict(),
            "windows": self.windows,
            "pedestrians": self.pedestrians,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        if d.get("format") != CALIBRATION_FORMAT:
            raise ValueError(f"calibration format {d.get('format')!r}, expected {CALIBRATION_FORMAT}")
        em = d.get("error_model")
        return cls(
            str(d["model"]),
            str(d["head"]),
            str(d["split"]),
            str(d["score"]),
            {str(k): tuple(float(x) for x in v) for k, v in d["thresholds"].items()},
            None if em is None else ErrorModel.from_dict(em),
            int(d["windows"]),
            int(d["pedestrians"]),
        )


def conformal_thresholds(scores: np.ndarray, levels: Sequence[float]) -> dict[str, tuple[float, ...]]:
    """Level key -> ``(P,)`` split-conformal thresholds of ``(M, P)`` scores, one per horizon step."""
    return {level_key(c): tuple(conformal_quantile(scores[:, h], c) for h in range(scores.shape[1])) for c in levels}


@dataclass(frozen=True)
class Coverage:
    """Coverage of a split's test windows: per level, window sums of covered positions.

    Attributes:
        covered: level key -> ``(W, P)`` covered scored pedestrians per window and step.
        raw: level key -> ``(W, P)`` the same for the model's own regions (``d ≤ sqrt(χ²₂(c))``; ``scaled`` only).
        counts: ``(W,)`` scored pedestrians per window (windows without any dropped).
        mean_radius_m: level key -> mean over positions of the calibrated region's equivalent radius (metres:
            the radius of the disc of equal area).
        nll_m: mean negative log-likelihood (nats per position, metres) of the Gaussians (``scaled`` only).
    """

    covered: dict[str, np.ndarray]
    raw: dict[str, np.ndarray]
    counts: np.ndarray
    mean_radius_m: dict[str, float]
    nll_m: float | None

    def pooled(self, key: str, raw: bool = False) -> PairedErrors:
        """Per-window sums over every step, for the pooled coverage and its interval."""
        sums = (self.raw if raw else self.covered)[key].sum(1)
        return PairedErrors(sums, self.counts * self.covered[key].shape[1])


def measure_coverage(calibration: Calibration, scored: ScoredForecasts, levels: Sequence[float] = LEVELS) -> Coverage:
    """Coverage of ``calibration``'s regions (and of the model's own) on forecasts ``scored`` (test windows)."""
    scores = region_scores(scored, calibration.score, calibration.error_model)
    keep = scored.counts > 0
    covered, raw, radius = {}, {}, {}
    sigma = rho = None
    if calibration.score == "scaled":
        sigma, rho = gaussians_of(scored, calibration.error_model)
    for c in levels:
        key = level_key(c)
        q = calibration.threshold(c)
        covered[key] = scored.window_sums(scores <= q[None, :])[keep]
        if sigma is not None and rho is not None:
            raw[key] = scored.window_sums(scores <= gaussian.chi2_radius(c))[keep]
            radius[key] = float(np.mean(q[None, :] * gaussian.equivalent_radius(sigma, rho)))
        else:
            radius[key] = float(np.mean(q))
    nll = None
    if sigma is not None and rho is not None:
        nll = float(np.mean(gaussian.nll(scored.error, sigma, rho)))
    return Coverage(covered, raw, scored.counts[keep], radius, nll)
