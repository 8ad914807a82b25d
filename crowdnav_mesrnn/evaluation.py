"""ADE/FDE of predictors on the leave-one-out test parts, with a true autoregressive rollout."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS, check_split
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.recordings import load_split
from crowdnav_mesrnn.data.windows import Window, collate, split_windows
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.gaussian import GaussianForecast
from crowdnav_mesrnn.stats import PairedErrors, average_ci, block_bootstrap_ci

#: ``(positions (B, T, N, 2) metres, mask (B, T, N)) -> (B, pred_len, N, 2) metres``; must read only
#: the first ``OBS_LEN`` steps.
BatchPredictFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

METRIC_KEYS = ("ade_m", "fde_m", "ade_norm", "fde_norm")


def batches(windows: Sequence[Window], batch_size: int, order: np.ndarray | None = None) -> Iterator[list[int]]:
    """Index batches of windows bucketed by size (less padding); ``order`` permutes the batches."""
    idx = np.argsort([w.num_peds for w in windows], kind="stable")
    chunks = [idx[i : i + batch_size].tolist() for i in range(0, len(idx), batch_size)]
    if order is not None:
        chunks = [chunks[i] for i in order[: len(chunks)]]
    yield from chunks


def cv_predict_batch(positions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Constant velocity for a batch: last observed displacement extrapolated (0 if unknown)."""
    last, prev = positions[:, OBS_LEN - 1], positions[:, OBS_LEN - 2]
    both = (mask[:, OBS_LEN - 1] & mask[:, OBS_LEN - 2]).unsqueeze(-1)
    vel = torch.where(both, last - prev, torch.zeros_like(last))
    k = torch.arange(1, PRED_LEN + 1, dtype=positions.dtype).view(1, PRED_LEN, 1, 1)
    return last.unsqueeze(1) + k * vel.unsqueeze(1)


def predicted_batches(
    predict: BatchPredictFn, windows: Sequence[Window], batch_size: int = 64
) -> Iterator[tuple[list[int], torch.Tensor, torch.Tensor, np.ndarray, torch.Tensor]]:
    """Roll ``predict`` out on ``windows`` in size-bucketed batches.

    Yields:
        ``(chunk, positions, present, scored, pred)``: the indices into ``windows``; positions
        ``(B, T, N, 2)`` metres and present ``(B, T, N)`` (tensors, :func:`collate`); scored ``(B, N)``
        bool array; the forecast ``(B, pred_len, N, 2)`` metres.
    """
    for chunk in batches(windows, batch_size):
        pos, pres, scored = collate([windows[i] for i in chunk])
        pos_t, pres_t = torch.from_numpy(pos), torch.from_numpy(pres)
        with torch.no_grad():
            pred = predict(pos_t, pres_t)
        yield chunk, pos_t, pres_t, scored, pred


def window_errors(
    predict: BatchPredictFn, windows: Sequence[Window], norm: MinMax, batch_size: int = 64
) -> dict[str, np.ndarray]:
    """Per-window sums over the scored pedestrians, in the order of ``windows``.

    Returns:
        ``{"ade_m", "fde_m", "ade_norm", "fde_norm"}``: ``(W,)`` float64 sums of each scored
        pedestrian's error (metres / min-max-normalised units), and ``"pedestrians"``: ``(W,)`` counts.
        Dividing a sum by the count total gives the split's ADE/FDE; paired differences of the sums
        feed :mod:`crowdnav_mesrnn.stats`.
    """
    out = {k: np.zeros(len(windows), np.float64) for k in METRIC_KEYS}
    out["pedestrians"] = np.zeros(len(windows), np.int64)
    scale = torch.as_tensor(norm.scale, dtype=torch.float32)
    for chunk, pos_t, _, scored, pred in predicted_batches(predict, windows, batch_size):
        err = pred.float() - pos_t[:, OBS_LEN:].float()
        d_m = err.norm(dim=-1)  # (B, P, N)
        d_n = (err * scale).norm(dim=-1)
        s = torch.from_numpy(scored).to(d_m.dtype)
        sums = {
            "ade_m": d_m.mean(1),
            "fde_m": d_m[:, -1],
            "ade_norm": d_n.mean(1),
            "fde_norm": d_n[:, -1],
        }
        for key, per_ped in sums.items():
            out[key][chunk] = (per_ped * s).sum(1).double().numpy()
        out["pedestrians"][chunk] = scored.sum(1)
    return out


#: ``(positions (B, T, N, 2) metres, mask (B, T, N)) -> GaussianForecast`` of the ``PRED_LEN`` future steps
#: (metres); must read only the first ``OBS_LEN`` steps.
DistributionFn = Callable[[torch.Tensor, torch.Tensor], GaussianForecast]
#: ``(positions, mask, samples) -> (B, samples, PRED_LEN, N, 2)`` metres; must read only the first ``OBS_LEN`` steps.
SampleFn = Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]


@dataclass(frozen=True)
class ScoredForecasts:
    """Forecasts of every scored pedestrian of a list of windows, one row per pedestrian (window order, then column
    order within a window), as :func:`collect_forecasts` gathers them.

    Attributes:
        error: ``(M, P, 2)`` float64 forecast (mean) minus true position, metres.
        speed: ``(M,)`` float64 length of the last observed displacement ``p(t) − p(t−1)``, metres per annotation
            step (0 when ``t−1`` is unobserved, as constant velocity assumes).
        window: ``(M,)`` int64 index of each row's window.
        num_windows: the number of windows (windows without a scored pedestrian have no row).
        sigma: ``(M, P, 2)`` float64 scales of each step's Gaussian, metres (None without a distribution).
        rho: ``(M, P)`` float64 correlations (None without a distribution).
        min_ade: ``(M,)`` float64 best-of-K ADE of each pedestrian, metres (None without samples).
        min_fde: ``(M,)`` float64 best-of-K FDE, metres, the sample chosen independently of ``min_ade``'s.
        observed: ``(M, P)`` bool, with ``rows="observed"`` (:func:`collect_forecasts`) only: step ``h``'s true
            position is observed with the pedestrian present in every frame through it (``error`` is 0 elsewhere);
            None when every row is scored (every step observed).
    """

    error: np.ndarray
    speed: np.ndarray
    window: np.ndarray
    num_windows: int
    sigma: np.ndarray | None = None
    rho: np.ndarray | None = None
    min_ade: np.ndarray | None = None
    min_fde: np.ndarray | None = None
    observed: np.ndarray | None = None

    @property
    def counts(self) -> np.ndarray:
        """``(W,)`` scored pedestrians per window."""
        return np.bincount(self.window, minlength=self.num_windows)

    def window_sums(self, values: np.ndarray) -> np.ndarray:
        """Per-window sums ``(W,)`` (or ``(W, P)``) of per-row values ``(M,)`` (or ``(M, P)``)."""
        values = np.asarray(values, dtype=np.float64)
        if values.ndim == 1:
            return np.bincount(self.window, weights=values, minlength=self.num_windows)
        return np.stack([self.window_sums(values[:, j]) for j in range(values.shape[1])], axis=1)


def collect_forecasts(
    windows: Sequence[Window],
    predict: BatchPredictFn | None = None,
    distribution: DistributionFn | None = None,
    sample: SampleFn | None = None,
    samples: int = 0,
    batch_size: int = 64,
    rows: str = "scored",
) -> ScoredForecasts:
    """Run a point forecast (``predict``) or a distribution (``distribution``; its means are the forecast) over
    ``windows`` and keep, per scored pedestrian, the error, the last observed speed, the Gaussians and, with
    ``sample`` and ``samples > 0``, the best-of-``samples`` ADE/FDE (per pedestrian, over its own samples).

    ``rows="observed"`` keeps every pedestrian present in all ``OBS_LEN`` observed frames instead (the scored ones
    and those who leave before the window ends), with ``observed`` marking the steps through which each stays
    present; the online conformal rule ``--reveal observed`` learns from them (no samples with this option)."""
    if (predict is None) == (distribution is None):
        raise ValueError("give exactly one of predict and distribution")
    if samples and sample is None:
        raise ValueError("samples > 0 needs a sample function")
    if rows not in ("scored", "observed"):
        raise ValueError(f"unknown rows {rows!r}; valid: scored, observed")
    if rows == "observed" and samples:
        raise ValueError("rows='observed' takes no samples")
    parts_observed: list[np.ndarray] = []
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("error", "speed", "window", "sigma", "rho", "ade", "fde")}
    for chunk in batches(windows, batch_size):
        pos, pres, scored = collate([windows[i] for i in chunk])
        pos_t, pres_t = torch.from_numpy(pos), torch.from_numpy(pres)
        with torch.no_grad():
            if distribution is not None:
                dist = distribution(pos_t, pres_t)
                mean = dist.mean
            else:
                assert predict is not None
                mean = predict(pos_t, pres_t)
            sampled = sample(pos_t, pres_t, samples) if samples and sample is not None else None
        if rows == "observed":
            through = np.cumprod(pres[:, OBS_LEN:], axis=1).astype(bool)  # (B, P, N): present at every step so far
            b_idx, n_idx = np.nonzero(pres[:, :OBS_LEN].all(axis=1))
            parts_observed.append(through.transpose(0, 2, 1)[b_idx, n_idx])
        else:
            b_idx, n_idx = np.nonzero(scored)
        truth = pos[:, OBS_LEN:]  # (B, P, N, 2)
        parts["error"].append((mean.double().numpy() - truth)[b_idx, :, n_idx])
        last, prev = pos[:, OBS_LEN - 1], pos[:, OBS_LEN - 2]
        both = pres[:, OBS_LEN - 1] & pres[:, OBS_LEN - 2]
        parts["speed"].append(np.where(both, np.hypot(*(last - prev).transpose(2, 0, 1)), 0.0)[b_idx, n_idx])
        parts["window"].append(np.asarray(chunk, dtype=np.int64)[b_idx])
        if distribution is not None:
            parts["sigma"].append(dist.sigma.double().numpy()[b_idx, :, n_idx])
            parts["rho"].append(dist.rho.double().numpy()[b_idx, :, n_idx])
        if sampled is not None:
            d = (sampled.double() - torch.from_numpy(truth).double()[:, None]).norm(dim=-1)  # (B, K, P, N)
            parts["ade"].append(d.mean(2).min(1).values.numpy()[b_idx, n_idx])
            parts["fde"].append(d[:, :, -1].min(1).values.numpy()[b_idx, n_idx])
    window = np.concatenate(parts["window"]) if parts["window"] else np.zeros(0, np.int64)
    order = np.argsort(window, kind="stable")

    def cat(key: str) -> np.ndarray | None:
        return np.concatenate(parts[key])[order] if parts[key] else None

    error = cat("error")
    speed = cat("speed")
    observed = np.concatenate(parts_observed)[order] if parts_observed else None
    if rows == "observed":
        if observed is None:
            observed = np.zeros((0, PRED_LEN), bool)
        assert error is not None or not len(observed)
        if error is not None:
            error = np.where(observed[..., None], error, 0.0)
    return ScoredForecasts(
        error if error is not None else np.zeros((0, PRED_LEN, 2)),
        speed if speed is not None else np.zeros(0),
        window[order],
        len(windows),
        cat("sigma"),
        cat("rho"),
        cat("ade"),
        cat("fde"),
        observed,
    )


def summarise(errors: dict[str, np.ndarray]) -> dict[str, float]:
    """ADE/FDE of a split from :func:`window_errors` (pedestrian-weighted means)."""
    peds = int(errors["pedestrians"].sum())
    out: dict[str, float] = {k: float(errors[k].sum()) / max(peds, 1) for k in METRIC_KEYS}
    out["windows"] = len(errors["pedestrians"])
    out["pedestrians"] = peds
    return out


def evaluate_windows(
    predict: BatchPredictFn, windows: Sequence[Window], norm: MinMax, batch_size: int = 64
) -> dict[str, float]:
    """ADE/FDE over the scored pedestrians of ``windows`` (metres, and min-max-normalised units)."""
    return summarise(window_errors(predict, windows, norm, batch_size))


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
#: Metrics of a distribution added by :func:`evaluate_model`, each with a ``_ci`` interval.
DISTRIBUTION_KEYS = ("nll_m", "min_ade_m", "min_fde_m")
#: Metrics whose paired differences :func:`paired_differences` gives (the point forecast's, then the distribution's).
PAIRED_KEYS = ("ade_m", "fde_m", *DISTRIBUTION_KEYS)


def distribution_metrics(
    scored: ScoredForecasts, block_len: int = 20, n_resamples: int = 10_000
) -> tuple[dict[str, float], dict[str, PairedErrors]]:
    """NLL (nats per position, metres, averaged over every scored pedestrian and step) and best-of-K ADE/FDE of
    one split, whichever ``scored`` holds, each with its block-bootstrap interval (``KEY_ci``), and the per-window
    sums behind them (for intervals of averages over splits)."""
    counts = scored.counts
    keep = counts > 0
    sums: dict[str, PairedErrors] = {}
    if scored.sigma is not None and scored.rho is not None:
        per_ped = gaussian.nll(scored.error, scored.sigma, scored.rho).mean(1)
        sums["nll_m"] = PairedErrors(scored.window_sums(per_ped)[keep], counts[keep])
    if scored.min_ade is not None and scored.min_fde is not None:
        sums["min_ade_m"] = PairedErrors(scored.window_sums(scored.min_ade)[keep], counts[keep])
        sums["min_fde_m"] = PairedErrors(scored.window_sums(scored.min_fde)[keep], counts[keep])
    out: dict[str, float] = {}
    for key, e in sums.items():
        out[key] = e.estimate
        out[f"{key}_ci"] = list(block_bootstrap_ci(e, block_len, n_resamples))  # type: ignore[assignment]
    return out, sums


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
    """Evaluate ``cv`` or a learned model on each split's ``part``; averaged over the splits.

    Args:
        checkpoint_for: ``split -> LearnedPredictor`` (default: the shipped pretrained weights of ``head``).
        window_sums: if given, filled with ``split ->`` :func:`window_errors` (windows in time order),
            for paired comparisons.
        samples: with a distribution head, also the best-of-``samples`` ADE/FDE (``min_ade_m``, ``min_fde_m``:
            per pedestrian, the closest of its samples, ADE and FDE chosen independently) with their
            block-bootstrap intervals; 0 for none.
        sampling: how samples are drawn (:data:`SAMPLINGS`).
        seed: seeds the samples (one stream per split).
        head: which shipped weights to load when ``checkpoint_for`` is None (``point`` or ``gaussian``).
        block_len: block length of the block bootstrap, in windows (:mod:`crowdnav_mesrnn.stats`).
        n_resamples: resamples of the block bootstrap.
        distribution_sums: if given, filled with ``split -> metric ->`` the per-window sums behind each metric of
            :data:`DISTRIBUTION_KEYS` (windows in time order), for :func:`paired_differences`.

    A model with a distribution head also gets ``nll_m``: the negative log-likelihood of the true positions under
    its Gaussians (nats per position, densities per m²), with its interval. Intervals of ``splits.average`` resample
    each split independently (:func:`crowdnav_mesrnn.stats.average_ci`).
    """
    splits = resolve_splits(splits)
    if sampling not in SAMPLINGS:
        raise ValueError(f"unknown sampling {sampling!r}; valid: {', '.join(SAMPLINGS)}")
    if samples < 0:
        raise ValueError(f"samples must be >= 0, got {samples}")
    if samples and model == "cv":
        raise ValueError("--samples needs a model with a distribution head; constant velocity forecasts one point")
    result: dict[str, Any] = {"model": model, "part": part, "splits": {}}
    if samples:
        result["samples"] = samples
        result["sampling"] = sampling
    dist_sums: dict[str, dict[str, PairedErrors]] = {}
    rngs = np.random.default_rng(seed).spawn(len(splits))
    for split, rng in zip(splits, rngs, strict=True):
        windows = split_windows(split, part, min_scored=min_scored, data_dir=data_dir)
        norm = split_norm(split, data_dir)
        predictor: Any = None
        if model == "cv":
            predict: BatchPredictFn = cv_predict_batch
        else:
            if checkpoint_for is None:
                from crowdnav_mesrnn.models.pretrained import load_pretrained

                predictor = load_pretrained(model, split, head=head)
            else:
                predictor = checkpoint_for(split)
            predict = predictor.predict_batch
            result.setdefault("checkpoints", {})[split] = predictor.info.get("selection") or predictor.info.get(
                "train_config"
            )
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
        independently (:func:`crowdnav_mesrnn.stats.average_ci`).

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
        lines.append(f"{'split':<9}" + "".join(f"{k:>26}" for k in extra))
        lines += _interval_rows(result["splits"], extra)
    for other, v in result.get("versus", {}).items():
        lines += ["", format_result(v["result"]), ""]
        keys = [k for k in PAIRED_KEYS if any(k in r for r in v["difference"].values())]
        lines.append(
            f"paired differences {result['model']} − {other} (the same windows; 95 % block-bootstrap intervals)"
        )
        lines.append(f"{'split':<9}" + "".join(f"{k:>26}" for k in keys))
        lines += _interval_rows(v["difference"], keys)
    return "\n".join(lines)


def _interval_rows(splits: Mapping[str, Mapping[str, Any]], keys: Sequence[str]) -> list[str]:
    """One row per split: each key's figure with its interval, ``-`` where the split lacks it."""
    rows = []
    for split, r in splits.items():
        cells = [f"{r[k]:.3f} [{r[k + '_ci'][0]:.3f}, {r[k + '_ci'][1]:.3f}]" if k in r else "-" for k in keys]
        rows.append(f"{split:<9}" + "".join(f"{c:>26}" for c in cells))
    return rows
