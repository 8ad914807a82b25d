"""The evaluation protocol: ADE/FDE of a predictor on the leave-one-out test (or val) parts with a true
autoregressive rollout, per split and averaged, the distribution metrics of a distribution head, and paired
differences between predictors with block-bootstrap intervals.

:func:`evaluate_model` is what ``crowdnav-mesrnn predictor evaluate`` runs; its result is a JSON-ready dict.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.data.constants import SPLITS, check_split
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.recordings import load_split
from crowdnav_mesrnn.data.windows import split_windows
from crowdnav_mesrnn.evaluation.metrics import (
    DISTRIBUTION_KEYS,
    METRIC_KEYS,
    BatchPredictFn,
    ScoredForecasts,
    collect_forecasts,
    cv_predict_batch,
    distribution_metrics,
    summarise,
    window_errors,
)
from crowdnav_mesrnn.evaluation.statistics import PairedErrors, average_ci, block_bootstrap_ci


def resolve_splits(splits: Sequence[str] | str) -> list[str]:
    """``"all"`` -> every split, a name -> ``[name]``; each checked (``ValueError`` naming the valid splits)."""
    if splits == "all":
        out = list(SPLITS)
    elif isinstance(splits, str):
        out = [splits]
    else:
        out = list(splits)
    for s in out:
        check_split(s)
    return out


def split_norm(split: str, data_dir: str | os.PathLike[str] | None = None) -> MinMax:
    """The split's normalisation, fitted on its training part (used for the normalised metric)."""
    return MinMax.fit_recordings(load_split(split, "train", data_dir))


#: Values of ``sampling`` in :func:`evaluate_model`: each step drawn from its Gaussian of the mean rollout
#: independently of the other steps (``marginal``, the protocol of Social-STGCNN's best-of-20), the same with one
#: draw per sample shared by all steps (``coherent``: whole trajectories at one quantile of every step's Gaussian),
#: or every draw fed back as the next input (``feedback``).
SAMPLINGS: tuple[str, ...] = ("marginal", "coherent", "feedback")
#: Metrics whose paired differences :func:`paired_differences` gives (the point forecast's, then the distribution's).
PAIRED_KEYS = ("ade_m", "fde_m", *DISTRIBUTION_KEYS)
#: Level of the calibrated regions whose coverage ``evaluate --samples`` reports (``coverage_90``).
COVERAGE_LEVEL = 0.9


def load_shipped(model: str, split: str, head: str = "point") -> Any:
    """The shipped predictor ``model`` of ``split``: the pretrained weights of ``head`` for a structural RNN, else
    the registry's predictor (:func:`crowdnav_mesrnn.predictors.load`; ``cv_gaussian``'s parameters of ``split``,
    which has a distribution whatever ``head`` says)."""
    if predictors.kind(model) == predictors.PRETRAINED:
        from crowdnav_mesrnn.models.pretrained import load_pretrained

        return load_pretrained(model, split, head=head)
    return predictors.load(model, split)


def predictor_record(predictor: Any) -> Any:
    """What a result says of the predictor used on a split: a checkpoint's selection or training config, or a fitted
    baseline's form and parameters."""
    info = getattr(predictor, "info", {}) or {}
    if "a_m" in info and "b_m" in info:
        return {k: info[k] for k in ("form", "a_m", "b_m") if k in info}
    return info.get("selection") or info.get("train_config")


def calibrated_coverage(
    predictor: Any,
    model: str,
    split: str,
    scored: ScoredForecasts,
    data_dir: str | os.PathLike[str] | None = None,
    min_scored: int = 2,
    batch_size: int = 64,
    level: float = COVERAGE_LEVEL,
) -> PairedErrors:
    """Per-window sums behind the coverage of the ``level`` regions of a distribution, calibrated by split conformal
    on ``split``'s validation windows with the ``scaled`` score (as ``calibrate --head gaussian``), on the forecasts
    ``scored`` (its test windows): each scored pedestrian counts the share of its steps covered, so the estimate is
    the fraction of covered positions, all steps pooled."""
    # The conformal primitives directly (crowdnav_mesrnn.uncertainty.calibration imports this module).
    from crowdnav_mesrnn.uncertainty.conformal import (
        Calibration,
        conformal_thresholds,
        level_key,
        measure_coverage,
        region_scores,
    )

    val = collect_forecasts(
        split_windows(split, "val", min_scored=min_scored, data_dir=data_dir),
        distribution=predictor.predict_distribution_batch,
        batch_size=batch_size,
    )
    thresholds = conformal_thresholds(region_scores(val, "scaled"), (level,))
    cal = Calibration(model, "gaussian", split, "scaled", thresholds, None, val.num_windows, len(val.speed))
    covered = measure_coverage(cal, scored, (level,)).covered[level_key(level)]  # (W, P) windows with a scored one
    return PairedErrors(covered.sum(1) / covered.shape[1], scored.counts[scored.counts > 0])


def evaluate_model(
    model: str,
    splits: Sequence[str] | str = "all",
    data_dir: str | os.PathLike[str] | None = None,
    checkpoint_for: Callable[[str], Any] | None = None,
    part: str = "test",
    min_scored: int = 2,
    batch_size: int = 64,
    window_sums: dict[str, dict[str, np.ndarray]] | None = None,
    samples: int = 0,
    sampling: str = "coherent",
    seed: int = 0,
    head: str = "point",
    block_len: int = 20,
    n_resamples: int = 10_000,
    distribution_sums: dict[str, dict[str, PairedErrors]] | None = None,
) -> dict[str, Any]:
    """Evaluate a shipped predictor (``cv``, ``cv_gaussian`` or a learned model) on each split's ``part``; averaged
    over the splits.

    Args:
        checkpoint_for: ``split -> LearnedPredictor`` (default: the shipped predictor, :func:`load_shipped`).
        window_sums: if given, filled with ``split ->`` :func:`window_errors` (windows in time order),
            for paired comparisons.
        samples: with a distribution, also (each with its block-bootstrap interval) the best-of-``samples`` ADE/FDE
            per pedestrian (``min_ade_m``, ``min_fde_m``: the closest of its own samples, ADE and FDE chosen
            independently) and per scene (``scene_min_ade_m``, ``scene_min_fde_m``: Social-GAN's, in each window
            the sample with the smallest error summed over its scored pedestrians), the energy score of each
            pedestrian's 12-step future (``energy_m``, metres; ``samples >= 2``) and, on the test part, the coverage
            of the 90 % regions calibrated on the split's validation windows (``coverage_90``,
            :func:`calibrated_coverage`); 0 for none.
        sampling: how samples are drawn (:data:`SAMPLINGS`).
        seed: seeds the samples (one stream per split).
        head: which shipped weights to load when ``checkpoint_for`` is None (``point`` or ``gaussian``).
        block_len: block length of the block bootstrap, in windows (:mod:`crowdnav_mesrnn.evaluation.statistics`).
        n_resamples: resamples of the block bootstrap.
        distribution_sums: if given, filled with ``split -> metric ->`` the per-window sums behind each metric of
            :data:`DISTRIBUTION_KEYS` (windows in time order), for :func:`paired_differences`.

    A model with a distribution head also gets ``nll_m``: the negative log-likelihood of the true positions under
    its Gaussians (nats per position, densities per m²), with its interval. Intervals of ``splits.average`` resample
    each split independently (:func:`crowdnav_mesrnn.evaluation.statistics.average_ci`).
    """
    splits = resolve_splits(splits)
    if sampling not in SAMPLINGS:
        raise ValueError(f"unknown sampling {sampling!r}; valid: {', '.join(SAMPLINGS)}")
    if samples < 0:
        raise ValueError(f"samples must be >= 0, got {samples}")
    baseline = predictors.kind(model) == predictors.BASELINE
    if samples and baseline:
        raise ValueError(
            f"--samples needs a model with a distribution; {model!r} forecasts one point (its distributional "
            "counterpart is cv_gaussian)"
        )
    result: dict[str, Any] = {"model": model, "part": part, "splits": {}}
    if samples:
        result["samples"] = samples
        result["sampling"] = sampling
        if part == "test":
            result["coverage"] = (
                f"coverage_90: the {COVERAGE_LEVEL:g} regions of the model's Gaussians, calibrated by split conformal "
                "(scaled score, per horizon step) on the split's validation windows; all 12 steps pooled"
            )
    dist_sums: dict[str, dict[str, PairedErrors]] = {}
    rngs = np.random.default_rng(seed).spawn(len(splits))
    for split, rng in zip(splits, rngs, strict=True):
        windows = split_windows(split, part, min_scored=min_scored, data_dir=data_dir)
        norm = split_norm(split, data_dir)
        predictor: Any = None
        if baseline:
            predict: BatchPredictFn = cv_predict_batch
        else:
            predictor = load_shipped(model, split, head) if checkpoint_for is None else checkpoint_for(split)
            predict = predictor.predict_batch
            result.setdefault("checkpoints", {})[split] = predictor_record(predictor)
        errors = window_errors(predict, windows, norm, batch_size)
        result["splits"][split] = summarise(errors)
        if window_sums is not None:
            window_sums[split] = errors
        if predictor is not None and predictor.has_distribution:
            gen = torch.Generator().manual_seed(int(rng.integers(2**62)))

            def draw(
                pos: torch.Tensor, mask: torch.Tensor, k: int, p: Any = predictor, g: torch.Generator = gen
            ) -> torch.Tensor:
                return p.sample_batch(pos, mask, k, g, feedback=sampling == "feedback", coherent=sampling == "coherent")

            scored = collect_forecasts(
                windows, distribution=predictor.predict_distribution_batch, sample=draw, samples=samples
            )
            metrics, dist_sums[split] = distribution_metrics(scored, block_len, n_resamples)
            if samples and part == "test":
                cov = calibrated_coverage(predictor, model, split, scored, data_dir, min_scored, batch_size)
                dist_sums[split]["coverage_90"] = cov
                metrics |= {
                    "coverage_90": cov.estimate,
                    "coverage_90_ci": list(block_bootstrap_ci(cov, block_len, n_resamples)),
                }
            result["splits"][split] |= metrics
            if distribution_sums is not None:
                distribution_sums[split] = dist_sums[split]
        elif samples:
            raise ValueError(
                f"--samples needs a distribution head; the {model!r} weights of split {split!r} have a point head "
                "(use the gaussian weights: --head gaussian, or a --checkpoint trained with head: gaussian)"
            )
    if len(splits) > 1:
        result["splits"]["average"] = {
            k: float(np.mean([result["splits"][s][k] for s in splits])) for k in METRIC_KEYS
        } | {
            "windows": sum(result["splits"][s]["windows"] for s in splits),
            "pedestrians": sum(result["splits"][s]["pedestrians"] for s in splits),
        }
        for key in DISTRIBUTION_KEYS:
            if all(key in dist_sums.get(s, {}) for s in splits):
                est, ci = average_ci([dist_sums[s][key] for s in splits], block_len, n_resamples)
                result["splits"]["average"] |= {key: est, f"{key}_ci": list(ci)}
    return result


def paired_differences(
    a: Mapping[str, Mapping[str, PairedErrors]],
    b: Mapping[str, Mapping[str, PairedErrors]],
    block_len: int = 20,
    n_resamples: int = 10_000,
) -> dict[str, dict[str, Any]]:
    """The paired differences A − B of two evaluations of the same windows, with block-bootstrap intervals.

    Args:
        a: ``split -> metric ->`` per-window sums of model A (:func:`paired_sums`).
        b: the same for model B (the same splits, part and windows as ``a``).

    Returns:
        ``split -> {metric: A − B, metric_ci: [lo, hi]}`` for every metric of :data:`PAIRED_KEYS` both hold (metres,
        nats per position for ``nll_m``); the windows are resampled
        together, so the interval is of the paired difference. Over two or more splits where every split holds the
        metric, ``average`` is the unweighted mean over the splits, its interval resampling each split
        independently (:func:`crowdnav_mesrnn.evaluation.statistics.average_ci`).

    Raises:
        ValueError: the two evaluations cover different splits or score different pedestrians in some window.
    """
    if list(a) != list(b):
        raise ValueError(f"the two evaluations cover different splits: {', '.join(a)} against {', '.join(b)}")
    out: dict[str, dict[str, Any]] = {}
    per_key: dict[str, list[PairedErrors]] = {}
    for split in a:
        out[split] = {}
        for key in PAIRED_KEYS:
            if key not in a[split] or key not in b[split]:
                continue
            ea, eb = a[split][key], b[split][key]
            if not np.array_equal(ea.count, eb.count):
                raise ValueError(
                    f"split {split!r}, {key}: the two evaluations score different pedestrians per window "
                    f"({len(ea.count)} windows, {int(ea.count.sum())} pedestrians against {len(eb.count)} windows, "
                    f"{int(eb.count.sum())} pedestrians); compare evaluations of the same split, part and windows"
                )
            diff = PairedErrors(ea.diff_sum - eb.diff_sum, ea.count)
            out[split] |= {key: diff.estimate, f"{key}_ci": list(block_bootstrap_ci(diff, block_len, n_resamples))}
            per_key.setdefault(key, []).append(diff)
    if len(a) > 1:
        out["average"] = {}
        for key, diffs in per_key.items():
            if len(diffs) == len(a):
                est, ci = average_ci(diffs, block_len, n_resamples)
                out["average"] |= {key: est, f"{key}_ci": list(ci)}
    return out


def paired_sums(
    window_sums: Mapping[str, Mapping[str, np.ndarray]], distribution_sums: Mapping[str, Mapping[str, PairedErrors]]
) -> dict[str, dict[str, PairedErrors]]:
    """``split -> metric ->`` per-window sums of every metric of :data:`PAIRED_KEYS` that :func:`evaluate_model`
    filled into ``window_sums`` (point ADE/FDE) and ``distribution_sums`` (NLL, best-of-K), windows without a scored
    pedestrian dropped as :func:`distribution_metrics` drops them."""
    out: dict[str, dict[str, PairedErrors]] = {}
    for split, ws in window_sums.items():
        keep = ws["pedestrians"] > 0
        out[split] = {k: PairedErrors(ws[k][keep], ws["pedestrians"][keep]) for k in ("ade_m", "fde_m")}
        out[split] |= dict(distribution_sums.get(split, {}))
    return out


def evaluate_versus(model: str, others: Sequence[str], **kwargs: Any) -> dict[str, Any]:
    """:func:`evaluate_model` of ``model`` and of each of ``others`` with the same arguments (shipped weights, the
    same head, samples, sampling, seed and bootstrap), and the paired differences ``model − other``.

    Each model's figures are exactly those of its own :func:`evaluate_model` run with these arguments. The returned
    result is ``model``'s, with ``versus: {other: {"result": other's result, "difference":``
    :func:`paired_differences` ``(model, other)}}``.

    Raises:
        ValueError: ``others`` is empty or names ``model`` or a model twice, or ``kwargs`` holds ``checkpoint_for``,
            ``window_sums`` or ``distribution_sums`` (the comparison is of shipped weights and fills those itself).
    """
    taken = {"checkpoint_for", "window_sums", "distribution_sums"} & set(kwargs)
    if taken:
        raise ValueError(f"evaluate_versus compares shipped weights and takes no {', '.join(sorted(taken))}")
    if not others or model in others or len(set(others)) != len(others):
        raise ValueError(f"versus needs other models than {model!r}, each once; got {', '.join(others) or 'none'}")

    def run(name: str) -> tuple[dict[str, Any], dict[str, dict[str, PairedErrors]]]:
        ws: dict[str, dict[str, np.ndarray]] = {}
        ds: dict[str, dict[str, PairedErrors]] = {}
        res = evaluate_model(name, window_sums=ws, distribution_sums=ds, **kwargs)
        return res, paired_sums(ws, ds)

    result, sums = run(model)
    block = {k: kwargs[k] for k in ("block_len", "n_resamples") if k in kwargs}
    result["versus"] = {}
    for other in others:
        res, other_sums = run(other)
        result["versus"][other] = {"result": res, "difference": paired_differences(sums, other_sums, **block)}
    return result


def format_result(result: dict[str, Any]) -> str:
    """A plain-text table of :func:`evaluate_model`'s result."""
    lines = [
        f"model {result['model']} on the {result['part']} parts (ADE/FDE over 12 steps; "
        "norm = paper's min-max-normalised units)",
        f"{'split':<9}{'ADE m':>8}{'FDE m':>8}{'ADE norm':>10}{'FDE norm':>10}{'windows':>9}{'peds':>7}",
    ]
    for split, r in result["splits"].items():
        lines.append(
            f"{split:<9}{r['ade_m']:>8.3f}{r['fde_m']:>8.3f}{r['ade_norm']:>10.4f}{r['fde_norm']:>10.4f}"
            f"{r['windows']:>9}{r['pedestrians']:>7}"
        )
    extra = [k for k in DISTRIBUTION_KEYS if any(k in r for r in result["splits"].values())]
    if extra:
        how = f" ({result['samples']} samples, {result['sampling']})" if "samples" in result else ""
        lines.append(f"distribution{how}; 95 % block-bootstrap intervals in brackets")
        lines += _interval_table(result["splits"], extra)
    for other, v in result.get("versus", {}).items():
        lines += ["", format_result(v["result"]), ""]
        keys = [k for k in PAIRED_KEYS if any(k in r for r in v["difference"].values())]
        lines.append(
            f"paired differences {result['model']} − {other} (the same windows; 95 % block-bootstrap intervals)"
        )
        lines += _interval_table(v["difference"], keys)
    return "\n".join(lines)


def _interval_table(splits: Mapping[str, Mapping[str, Any]], keys: Sequence[str], per_row: int = 4) -> list[str]:
    """A header and :func:`_interval_rows` for every ``per_row`` keys (so a table stays under 120 characters)."""
    lines: list[str] = []
    for i in range(0, len(keys), per_row):
        part = keys[i : i + per_row]
        lines.append(f"{'split':<9}" + "".join(f"{k:>26}" for k in part))
        lines += _interval_rows(splits, part)
    return lines


def _interval_rows(splits: Mapping[str, Mapping[str, Any]], keys: Sequence[str]) -> list[str]:
    """One row per split: each key's figure with its interval, ``-`` where the split lacks it."""
    rows = []
    for split, r in splits.items():
        cells = [f"{r[k]:.3f} [{r[k + '_ci'][0]:.3f}, {r[k + '_ci'][1]:.3f}]" if k in r else "-" for k in keys]
        rows.append(f"{split:<9}" + "".join(f"{c:>26}" for c in cells))
    return rows
