"""ADE/FDE of predictors on the leave-one-out test parts, with a true autoregressive rollout."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
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
    """

    error: np.ndarray
    speed: np.ndarray
    window: np.ndarray
    num_windows: int
    sigma: np.ndarray | None = None
    rho: np.ndarray | None = None
    min_ade: np.ndarray | None = None
    min_fde: np.ndarray | None = None

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
) -> ScoredForecasts:
    """Run a point forecast (``predict``) or a distribution (``distribution``; its means are the forecast) over
    ``windows`` and keep, per scored pedestrian, the error, the last observed speed, the Gaussians and, with
    ``sample`` and ``samples > 0``, the best-of-``samples`` ADE/FDE (per pedestrian, over its own samples)."""
    if (predict is None) == (distribution is None):
        raise ValueError("give exactly one of predict and distribution")
    if samples and sample is None:
        raise ValueError("samples > 0 needs a sample function")
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
    return ScoredForecasts(
        error if error is not None else np.zeros((0, PRED_LEN, 2)),
        speed if speed is not None else np.zeros(0),
        window[order],
        len(windows),
        cat("sigma"),
        cat("rho"),
        cat("ade"),
        cat("fde"),
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
        for split, r in result["splits"].items():
            cells = [f"{r[k]:.3f} [{r[k + '_ci'][0]:.3f}, {r[k + '_ci'][1]:.3f}]" if k in r else "-" for k in extra]
            lines.append(f"{split:<9}" + "".join(f"{c:>26}" for c in cells))
    return "\n".join(lines)
