"""Calibrated uncertainty regions around forecasts: split conformal prediction on validation windows, coverage
on the held-out scene (``crowdnav-mesrnn predictor calibrate``).

The scores, thresholds and regions are :mod:`crowdnav_mesrnn.uncertainty.conformal`'s. ``method="online"`` tracks
the thresholds over the test scene instead (:mod:`crowdnav_mesrnn.uncertainty.online_conformal`).

Why ``scaled`` is the default score (chosen before any coverage was measured): the validation windows come from
the four training scenes and the test windows from the held-out one, and the scenes differ in how far people
move per annotation step (``biwi_eth`` is annotated every 0.667 s, the others every 0.4 s; walking speeds
differ between scenes). A disc fitted in metres on the four transfers its typical error to the fifth
unchanged; a scale on a region that grows with the observed displacement (or with the model's own
uncertainty) transfers the relation between the two instead. ``radius`` is kept as the plain comparison.

Conformal step: on the validation windows (the ``_val`` pieces of the training scenes; never the test scene),
per horizon step ``h``, ``q_h(c)`` is the split-conformal threshold of the scores. Test and validation pedestrians
are not exchangeable (another scene, and overlapping windows), so coverage is measured on the held-out scene's test
windows, per step and pooled, with block-bootstrap intervals (:mod:`crowdnav_mesrnn.evaluation.statistics`: windows
overlap, so blocks of consecutive windows are resampled).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn.data.constants import PRED_LEN, check_split
from crowdnav_mesrnn.data.windows import Window, split_windows
from crowdnav_mesrnn.evaluation.metrics import ScoredForecasts, collect_forecasts, cv_predict_batch
from crowdnav_mesrnn.evaluation.protocol import load_shipped, predictor_record, resolve_splits
from crowdnav_mesrnn.evaluation.statistics import (
    DEFAULT_BLOCK_LEN,
    DEFAULT_RESAMPLES,
    PairedErrors,
    average_ci,
    block_bootstrap_ci,
)
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.uncertainty.conformal import (
    LEVELS,
    SCORES,
    Calibration,
    Coverage,
    ErrorModel,
    conformal_thresholds,
    level_key,
    measure_coverage,
    region_scores,
)
from crowdnav_mesrnn.uncertainty.online_conformal import (
    EXPERT_INTERVAL,
    GAMMA_GRID,
    GAMMA_RULES,
    GAMMA_TOLERANCE,
    REVEAL_RULES,
    OnlineResult,
    expert_rates,
    online_for_split,
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
    """Constant velocity, or a shipped predictor with weights or parameters per split (:func:`load_shipped`: a
    structural RNN's weights of ``head``, ``cv_gaussian``'s distribution) unless ``predictor`` is given."""
    if model == "cv":
        if head != "point":
            raise ValueError("constant velocity has only a point forecast (head point)")
        return Forecaster("cv", "point", point=cv_predict_batch)
    if predictor is None:
        predictor = load_shipped(model, split, head)
    info = predictor_record(predictor)
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
    (:data:`crowdnav_mesrnn.uncertainty.online_conformal.REVEAL_RULES`); the result records it. ``gamma_rule`` (online only;
    default ``"validation"``) sets the step size: one chosen on validation, or ``"experts"``, every step size of the
    grid mixed online (:data:`crowdnav_mesrnn.uncertainty.online_conformal.GAMMA_RULES`); an ``"experts"`` row also holds
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
