"""Calibrated uncertainty regions around forecasts: split conformal prediction on validation windows.

Every forecast step of every pedestrian gets a region ``{y : score(y) ≤ q_h(c)}`` meant to hold the true
position with probability ``c`` (levels 0.5, 0.9, 0.95). Two scores:

- ``scaled`` (the default): the Mahalanobis distance ``d`` of the true position under the forecast's Gaussian
  at that step, so the region is the Gaussian's own ellipse scaled by ``q_h(c)`` (the model's region is
  ``d ≤ sqrt(χ²₂(c))``; conformal calibration replaces that radius by ``q_h(c)``). A model with the distribution
  head (``head: gaussian``) supplies its Gaussians. A point forecast (constant velocity, today's point weights)
  gets an **error model** fitted on the split's training windows: an isotropic Gaussian whose scale grows with
  the pedestrian's last observed displacement, ``σ_h(v) = a_h + b_h v`` (``v`` in metres per annotation
  step, ``a_h, b_h ≥ 0`` by non-negative least squares of the errors' lengths, whose mean is ``σ sqrt(π/2)``
  for an isotropic Gaussian). The regions then widen with speed, horizon and the recording's step time.
- ``radius``: the error's length; the region is a disc of radius ``q_h(c)`` metres, the same for everyone.

Why ``scaled`` is the default (chosen before any coverage was measured): the validation windows come from
the four training scenes and the test windows from the held-out one, and the scenes differ in how far people
move per annotation step (``biwi_eth`` is annotated every 0.667 s, the others every 0.4 s; walking speeds
differ between scenes). A disc fitted in metres on the four transfers its typical error to the fifth
unchanged; a scale on a region that grows with the observed displacement (or with the model's own
uncertainty) transfers the relation between the two instead. ``radius`` is kept as the plain comparison.

Conformal step: on the validation windows (the ``_val`` pieces of the training scenes; never the test scene),
per horizon step ``h``, ``q_h(c)`` is the ``⌈(n + 1) c⌉``-th smallest of the ``n`` scores (split conformal
prediction; infinite when that exceeds ``n``). It would guarantee coverage ``≥ c`` if test and validation
pedestrians were exchangeable; they are not (another scene, and overlapping windows), so coverage is measured
on the held-out scene's test windows, per step and pooled, with block-bootstrap intervals
(:mod:`crowdnav_mesrnn.evaluation.statistics`: windows overlap, so blocks of consecutive windows are resampled).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

import numpy as np
from scipy.optimize import nnls

from crowdnav_mesrnn.data.constants import PRED_LEN, check_split
from crowdnav_mesrnn.data.windows import Window, split_windows
from crowdnav_mesrnn.evaluation.metrics import ScoredForecasts, collect_forecasts, cv_predict_batch
from crowdnav_mesrnn.evaluation.protocol import resolve_splits
from crowdnav_mesrnn.evaluation.statistics import (
    DEFAULT_BLOCK_LEN,
    DEFAULT_RESAMPLES,
    PairedErrors,
    average_ci,
    block_bootstrap_ci,
)
from crowdnav_mesrnn.models import gaussian

if TYPE_CHECKING:
    from crowdnav_mesrnn.online_conformal import OnlineResult

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
        if sigma is None or rho is None:
            if self.error_model is None:
                raise ValueError(f"the {self.model} calibration needs the forecasts' own Gaussians (sigma, rho)")
            return q * self.error_model.sigma(speed)
        return q * gaussian.major_semi_axis(np.asarray(sigma, np.float64), np.asarray(rho, np.float64))

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


# ------------------------------------------------------------------------------------------------ fitting
@dataclass(frozen=True)
class Forecaster:
    """How to forecast a batch of windows: a point function, or a distribution function (gaussian head)."""

    model: str
    head: str
    point: Callable[[Any, Any], Any] | None = None
    distribution: Callable[[Any, Any], Any] | None = None
    info: dict[str, Any] | None = None

    def collect(self, windows: Sequence[Window], batch_size: int = 64, rows: str = "scored") -> ScoredForecasts:
        """:func:`crowdnav_mesrnn.evaluation.metrics.collect_forecasts` of ``windows`` (``rows`` as there)."""
        return collect_forecasts(windows, self.point, self.distribution, batch_size=batch_size, rows=rows)


def forecaster_for(model: str, split: str, head: str = "point", predictor: Any = None) -> Forecaster:
    """Constant velocity, or a learned predictor (the shipped weights of ``head`` unless ``predictor`` is given)."""
    if model == "cv":
        if head != "point":
            raise ValueError("constant velocity has only a point forecast (head point)")
        return Forecaster("cv", "point", point=cv_predict_batch)
    if predictor is None:
        from crowdnav_mesrnn.models.pretrained import load_pretrained

        predictor = load_pretrained(model, split, head=head)
    info = predictor.info.get("selection") or predictor.info.get("train_config")
    if predictor.has_distribution:
        return Forecaster(model, "gaussian", distribution=predictor.predict_distribution_batch, info=info)
    return Forecaster(model, "point", point=predictor.predict_batch, info=info)


def calibration_scores(
    forecaster: Forecaster,
    split: str,
    score: str = "scaled",
    data_dir: str | os.PathLike[str] | None = None,
    min_scored: int = 2,
    batch_size: int = 64,
) -> tuple[ErrorModel | None, list[Window], ScoredForecasts, np.ndarray]:
    """The error model (``scaled`` point forecasts: fitted on the split's training windows), the split's validation
    windows, their forecasts and their ``(M, P)`` conformal scores. The test windows are never read."""
    check_split(split)
    if score not in SCORES:
        raise ValueError(f"unknown score {score!r}; valid: {', '.join(SCORES)}")
    error_model = None
    if score == "scaled" and forecaster.distribution is None:
        train = split_windows(split, "train", min_scored, data_dir)
        error_model = ErrorModel.fit(forecaster.collect(train, batch_size))
    windows = split_windows(split, "val", min_scored, data_dir)
    val = forecaster.collect(windows, batch_size)
    return error_model, windows, val, region_scores(val, score, error_model)


def conformal_thresholds(scores: np.ndarray, levels: Sequence[float]) -> dict[str, tuple[float, ...]]:
    """Level key -> ``(P,)`` split-conformal thresholds of ``(M, P)`` scores, one per horizon step."""
    return {level_key(c): tuple(conformal_quantile(scores[:, h], c) for h in range(scores.shape[1])) for c in levels}


def fit_calibration(
    forecaster: Forecaster,
    split: str,
    score: str = "scaled",
    levels: Sequence[float] = LEVELS,
    data_dir: str | os.PathLike[str] | None = None,
    min_scored: int = 2,
    batch_size: int = 64,
) -> Calibration:
    """Fit the error model (``scaled`` point forecasts: on the split's training windows) and the conformal
    thresholds (on its validation windows). The test windows are never read."""
    error_model, _, val, scores = calibration_scores(forecaster, split, score, data_dir, min_scored, batch_size)
    return calibration_from_scores(forecaster, split, score, levels, error_model, val, scores)


def calibration_from_scores(
    forecaster: Forecaster,
    split: str,
    score: str,
    levels: Sequence[float],
    error_model: ErrorModel | None,
    val: ScoredForecasts,
    scores: np.ndarray,
) -> Calibration:
    """The :class:`Calibration` of :func:`calibration_scores`' output."""
    return Calibration(
        forecaster.model,
        forecaster.head,
        split,
        score,
        conformal_thresholds(scores, levels),
        error_model,
        val.num_windows,
        len(val.speed),
    )


# ------------------------------------------------------------------------------------------------ coverage
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


def coverage_fields(
    cov: Coverage, levels: Sequence[float], block_len: int = DEFAULT_BLOCK_LEN, n_resamples: int = DEFAULT_RESAMPLES
) -> dict[str, Any]:
    """``coverage``, ``coverage_ci``, ``coverage_per_step`` (and the raw ones) of a split's row."""
    row: dict[str, Any] = {"coverage": {}, "coverage_ci": {}, "coverage_per_step": {}}
    for c in levels:
        key = level_key(c)
        pooled = cov.pooled(key)
        row["coverage"][key] = pooled.estimate
        row["coverage_ci"][key] = list(block_bootstrap_ci(pooled, block_len, n_resamples))
        row["coverage_per_step"][key] = (cov.covered[key].sum(0) / cov.counts.sum()).tolist()
    if cov.raw:
        row["raw_coverage"] = {k: cov.pooled(k, raw=True).estimate for k in cov.raw}
        row["raw_coverage_per_step"] = {k: (v.sum(0) / cov.counts.sum()).tolist() for k, v in cov.raw.items()}
    return row


def average_fields(
    covs: Sequence[Coverage],
    rows: Sequence[dict[str, Any]],
    levels: Sequence[float],
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
) -> dict[str, Any]:
    """The unweighted mean over splits of :func:`coverage_fields` (intervals resample each split independently)."""
    avg: dict[str, Any] = {"coverage": {}, "coverage_ci": {}, "coverage_per_step": {}}
    for c in levels:
        key = level_key(c)
        est, ci = average_ci([cov.pooled(key) for cov in covs], block_len, n_resamples)
        avg["coverage"][key] = est
        avg["coverage_ci"][key] = list(ci)
        avg["coverage_per_step"][key] = np.mean([r["coverage_per_step"][key] for r in rows], axis=0).tolist()
    if all("raw_coverage" in r for r in rows):
        avg["raw_coverage"] = {k: float(np.mean([r["raw_coverage"][k] for r in rows])) for k in rows[0]["raw_coverage"]}
    return avg


def _mean_of(rows: Sequence[dict[str, Any]], field: str) -> dict[str, float]:
    return {k: float(np.mean([r[field][k] for r in rows])) for k in rows[0][field]}


def calibrate_model(
    model: str,
    splits: Sequence[str] | str = "all",
    score: str = "scaled",
    head: str = "point",
    levels: Sequence[float] = LEVELS,
    data_dir: str | os.PathLike[str] | None = None,
    predictor_for: Callable[[str], Any] | None = None,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    method: str = "split",
    reveal: str | None = None,
    gamma_rule: str | None = None,
) -> dict[str, Any]:
    """Calibrate on each split's validation windows, measure coverage on its test windows, and average.

    Returns ``{"model", "head", "score", "levels", "splits": {split: {...}, "average": {...}}}``; each split holds
    ``coverage`` (level key -> fraction of true positions inside the calibrated regions, all steps pooled),
    ``coverage_ci`` (95 % block-bootstrap intervals), ``coverage_per_step`` (level key -> ``P`` fractions),
    ``raw_coverage`` / ``raw_coverage_per_step`` (the model's own regions, ``scaled`` only), ``thresholds``,
    ``mean_radius_m``, ``nll_m`` (``scaled`` only), ``windows``, ``pedestrians``, ``calibration_windows`` and
    ``calibration_pedestrians``. ``average`` is the unweighted mean over the splits (intervals resample each
    split independently).

    ``method="online"`` (:mod:`crowdnav_mesrnn.online_conformal`) tracks each step's threshold over the test scene
    in time order from the split-conformal one, with delayed feedback; the coverage fields are then the tracker's,
    ``thresholds`` are its starting ones, and each split also holds ``method``-specific fields: ``gamma`` and
    ``gamma_validation_deviation`` (the step size chosen on validation and every candidate's deviation),
    ``coverage_min_step``, ``coverage_second_half``, ``thresholds_end``, ``mean_radius_diff_m`` with
    ``mean_radius_diff_ci`` (online minus split conformal, paired by window) and ``split_conformal`` (its
    coverage, per-step coverage and mean radius on the same windows). ``reveal`` (online only; default
    ``"window"``, the strictly causal rule) is when an outcome updates the tracker
    (:data:`crowdnav_mesrnn.online_conformal.REVEAL_RULES`); the result records it. ``gamma_rule`` (online only;
    default ``"validation"``) sets the step size: one chosen on validation, or ``"experts"``, every step size of the
    grid mixed online (:data:`crowdnav_mesrnn.online_conformal.GAMMA_RULES`); an ``"experts"`` row also holds
    ``expert_weights_end`` (level key -> ``P`` lists of the experts' final weights).
    """
    if method not in ("split", "online"):
        raise ValueError(f"unknown calibration method {method!r}; valid: split, online")
    if method == "split" and reveal is not None:
        raise ValueError(f"reveal={reveal!r} applies to method 'online' only, not {method!r}")
    if method == "split" and gamma_rule is not None:
        raise ValueError(f"gamma_rule={gamma_rule!r} applies to method 'online' only, not {method!r}")
    splits = resolve_splits(splits)
    levels = tuple(float(c) for c in levels)
    for c in levels:
        gaussian.chi2_radius(c)  # validates the level
    description = (
        "split conformal on the split's validation windows, per horizon step; coverage on its test windows"
        if method == "split"
        else "online conformal (a quantile tracker per horizon step and level, delayed feedback) over the test "
        "scene in time order, from split conformal's thresholds on the split's validation windows, step size "
        "chosen on the validation scenes; coverage on its test windows"
    )
    out: dict[str, Any] = {
        "model": model,
        "head": head,
        "score": score,
        "levels": list(levels),
        "calibration": description
        + ("; point forecasts: an error model fitted on its training windows" if score == "scaled" else ""),
        "splits": {},
    }
    if method == "online":
        from crowdnav_mesrnn.online_conformal import (
            EXPERT_INTERVAL,
            GAMMA_GRID,
            GAMMA_RULES,
            GAMMA_TOLERANCE,
            REVEAL_RULES,
            expert_rates,
            online_for_split,
        )

        reveal = REVEAL_RULES[0] if reveal is None else reveal
        if reveal not in REVEAL_RULES:
            raise ValueError(f"unknown reveal rule {reveal!r}; valid: {', '.join(REVEAL_RULES)}")
        experts = gamma_rule == "experts"
        if gamma_rule is not None and gamma_rule not in GAMMA_RULES:
            raise ValueError(f"unknown gamma rule {gamma_rule!r}; valid: {', '.join(GAMMA_RULES)}")
        if reveal == "observed" and not experts:
            raise ValueError(
                "reveal='observed' runs with the step-size experts only: add gamma_rule='experts' (--gamma experts)"
            )
        out["calibration"] += f"; outcomes revealed {_REVEAL_TEXT[reveal]}"
        if experts:
            out["calibration"] = out["calibration"].replace(
                "step size chosen on the validation scenes",
                "every step size of the grid as an expert, mixed by their pinball loss on the revealed outcomes",
            )
        out = {
            "method": "online",
            "reveal": reveal,
            **({"gamma_rule": "experts"} if experts else {}),
            **out,
            "gamma_grid": list(GAMMA_GRID),
        }
        if experts:
            rates = {level_key(c): expert_rates(len(GAMMA_GRID), c) for c in levels}
            out |= {
                "expert_interval": EXPERT_INTERVAL,
                "expert_eta": {k: r[0] for k, r in rates.items()},
                "expert_share": next(iter(rates.values()))[1],
            }
        else:
            out["gamma_tolerance"] = GAMMA_TOLERANCE
    per_split: dict[str, Coverage] = {}
    for split in splits:
        predictor = predictor_for(split) if predictor_for is not None else None
        forecaster = forecaster_for(model, split, head, predictor)
        out["head"] = forecaster.head
        error_model, val_windows, val, val_scores = calibration_scores(forecaster, split, score, data_dir)
        cal = calibration_from_scores(forecaster, split, score, levels, error_model, val, val_scores)
        test_windows = split_windows(split, "test", 2, data_dir)
        test = forecaster.collect(test_windows)
        cov = measure_coverage(cal, test, levels)
        online = None
        if method == "online":
            online = online_for_split(
                cal,
                val_windows,
                val,
                val_scores,
                test_windows,
                test,
                cov,
                levels,
                data_dir,
                reveal,
                "experts" if experts else "validation",
                _feedback_forecasts(forecaster, split, data_dir) if reveal == "observed" else None,
            )
            split_cov, cov = cov, online.coverage
        per_split[split] = cov
        row = coverage_fields(cov, levels, block_len, n_resamples)
        row["thresholds"] = {k: list(v) for k, v in cal.thresholds.items()}
        row["mean_radius_m"] = cov.mean_radius_m
        if cov.nll_m is not None:
            row["nll_m"] = cov.nll_m
        if cal.error_model is not None:
            row["error_model"] = cal.error_model.to_dict()
        row |= {
            "windows": len(cov.counts),
            "pedestrians": int(cov.counts.sum()),
            "calibration_windows": cal.windows,
            "calibration_pedestrians": cal.pedestrians,
        }
        if online is not None:
            row |= _online_fields(online, split_cov, levels, block_len, n_resamples)
        if forecaster.info:
            out.setdefault("checkpoints", {})[split] = forecaster.info
        out["splits"][split] = row
    if len(splits) > 1:
        rows = [out["splits"][s] for s in splits]
        avg = average_fields([per_split[s] for s in splits], rows, levels, block_len, n_resamples)
        avg["mean_radius_m"] = _mean_of(rows, "mean_radius_m")
        if all("nll_m" in r for r in rows):
            avg["nll_m"] = float(np.mean([r["nll_m"] for r in rows]))
        avg["windows"] = sum(r["windows"] for r in rows)
        avg["pedestrians"] = sum(r["pedestrians"] for r in rows)
        if method == "online":
            avg["coverage_min_step"] = {k: min(v) for k, v in avg["coverage_per_step"].items()}
            avg["worst_split_min_step"] = {k: min(r["coverage_min_step"][k] for r in rows) for k in avg["coverage"]}
            avg["coverage_second_half"] = _mean_of(rows, "coverage_second_half")
            avg["mean_radius_diff_m"] = _mean_of(rows, "mean_radius_diff_m")
            split_rows = [r["split_conformal"] for r in rows]
            split_steps = {k: np.mean([r["coverage_per_step"][k] for r in split_rows], axis=0) for k in avg["coverage"]}
            avg["split_conformal"] = {
                "coverage": _mean_of(split_rows, "coverage"),
                "coverage_per_step": {k: v.tolist() for k, v in split_steps.items()},
                "coverage_min_step": {k: float(v.min()) for k, v in split_steps.items()},
                "worst_split_min_step": {
                    k: min(r["coverage_min_step"][k] for r in split_rows) for k in avg["coverage"]
                },
                "mean_radius_m": _mean_of(split_rows, "mean_radius_m"),
            }
        out["splits"]["average"] = avg
    return out


def _feedback_forecasts(
    forecaster: Forecaster, split: str, data_dir: str | os.PathLike[str] | None
) -> tuple[list[Window], ScoredForecasts]:
    """Every test window of ``split`` (whether or not it has a scored pedestrian) and its forecasts of every pedestrian
    present through the observation: what ``--reveal observed`` learns from."""
    windows = split_windows(split, "test", 0, data_dir)
    return windows, forecaster.collect(windows, rows="observed")


#: How each reveal rule of the online method reads in the result's ``calibration`` text.
_REVEAL_TEXT: Final[dict[str, str]] = {
    "window": f"per window, once its scored pedestrians are known (all steps at t + {PRED_LEN}; strictly causal)",
    "step": f"per step (step h at t + h, counting only pedestrians still present at t + {PRED_LEN}: optimistic)",
    "observed": "per step (step h at t + h, over every pedestrian present from the window's first frame through "
    "t + h, scored or not; strictly causal)",
}


def _online_fields(
    online: OnlineResult, split_cov: Coverage, levels: Sequence[float], block_len: int, n_resamples: int
) -> dict[str, Any]:
    """The fields only ``method="online"`` rows have (:func:`calibrate_model`)."""
    keys = [level_key(c) for c in levels]
    split_row = coverage_fields(split_cov, levels, block_len, n_resamples)
    cov = online.coverage
    per_step = {k: cov.covered[k].sum(0) / cov.counts.sum() for k in keys}
    diffs = {k: PairedErrors(online.radius_diff[k], cov.counts * cov.covered[k].shape[1]) for k in keys}
    extra = {} if online.expert_weights_end is None else {"expert_weights_end": online.expert_weights_end}
    return extra | {
        "gamma": online.gamma,
        "gamma_validation_deviation": online.gamma_deviation,
        "coverage_min_step": {k: float(per_step[k].min()) for k in keys},
        "coverage_second_half": online.second_half,
        "thresholds_end": online.thresholds_end,
        "mean_radius_diff_m": {k: diffs[k].estimate for k in keys},
        "mean_radius_diff_ci": {k: list(block_bootstrap_ci(diffs[k], block_len, n_resamples)) for k in keys},
        "split_conformal": {
            "coverage": split_row["coverage"],
            "coverage_ci": split_row["coverage_ci"],
            "coverage_per_step": split_row["coverage_per_step"],
            "coverage_min_step": {k: min(v) for k, v in split_row["coverage_per_step"].items()},
            "mean_radius_m": split_cov.mean_radius_m,
        },
    }


def format_calibration(result: dict[str, Any]) -> str:
    """A plain-text table of :func:`calibrate_model`'s result."""
    keys = [level_key(c) for c in result["levels"]]
    lines = [
        f"model {result['model']} ({result['head']} head), score {result['score']}: {result['calibration']}",
        "coverage of the calibrated regions on test (all 12 steps pooled), [95 % block-bootstrap interval], "
        "the lowest-highest step, and the model's own regions (raw)",
        f"{'split':<9}" + "".join(f"{'cov ' + k:>34}" for k in keys) + "".join(f"{'raw ' + k:>9}" for k in keys),
    ]
    for split, r in result["splits"].items():
        cells = []
        for k in keys:
            ci = r["coverage_ci"][k]
            steps = r["coverage_per_step"][k]
            cells.append(f"{r['coverage'][k]:.3f} [{ci[0]:.3f}, {ci[1]:.3f}] {min(steps):.2f}-{max(steps):.2f}")
        raw = [f"{r['raw_coverage'][k]:.3f}" if "raw_coverage" in r else "-" for k in keys]
        lines.append(f"{split:<9}" + "".join(f"{c:>34}" for c in cells) + "".join(f"{c:>9}" for c in raw))
    lines.append(
        "mean equivalent radius of the calibrated regions (m): "
        + "; ".join(
            f"{s} " + "/".join(f"{r['mean_radius_m'][k]:.2f}" for k in keys) for s, r in result["splits"].items()
        )
    )
    if result.get("method") == "online":
        lines.append(
            "split conformal on the same windows, coverage (lowest step) and mean radius (m) per level; the online "
            + (
                "experts' step sizes weighted by their final weights (mean over steps) per level:"
                if result.get("gamma_rule") == "experts"
                else "step size gamma per level:"
            )
        )
        for split, r in result["splits"].items():
            sc = r["split_conformal"]
            cells = [
                f"{k}: {sc['coverage'][k]:.3f} ({sc['coverage_min_step'][k]:.2f}) {sc['mean_radius_m'][k]:.2f} m"
                for k in keys
            ]
            gam = " gamma " + "/".join(f"{r['gamma'][k]:g}" for k in keys) if "gamma" in r else ""
            lines.append(f"{split:<9}" + "; ".join(cells) + gam)
    return "\n".join(lines)
