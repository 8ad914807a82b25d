"""How forecasts of windows are scored: batching, rollouts, per-window ADE/FDE sums and per-pedestrian errors.

A forecast is a :data:`BatchPredictFn` (or a :data:`DistributionFn`) over padded window batches in metres; it must
read only the first ``OBS_LEN`` steps. Scored pedestrians are those present in all 20 steps of a window. Errors are
summed per window (never averaged), so a split's figure is a ratio of sums and blocks of windows can be resampled
(:mod:`crowdnav_mesrnn.evaluation.statistics`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.windows import Window, collate
from crowdnav_mesrnn.evaluation.statistics import PairedErrors, block_bootstrap_ci
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.gaussian import GaussianForecast

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

    A labelled progress bar (stderr) appears when the windows take over two seconds.
    """
    from tqdm.auto import tqdm

    groups = list(batches(windows, batch_size))
    desc = f"forecasting {len(windows):,} windows"
    for chunk in tqdm(groups, desc=desc, unit="batch", delay=2.0, leave=False):
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
        feed :mod:`crowdnav_mesrnn.evaluation.statistics`.
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
        energy: ``(M,)`` float64 energy score of each pedestrian's 12-step future from its samples
            (:func:`energy_score`), metres (None without samples, or with fewer than 2).
        scene_min_ade: ``(W,)`` float64 per window, ``min_k Σ_i ADE_ik`` over its scored pedestrians ``i``, sample
            ``k`` shared by all of them (Social-GAN's per-scene best-of-K), metres; 0 for a window without a scored
            pedestrian (None without samples).
        scene_min_fde: ``(W,)`` the same for FDE, its sample chosen independently of ``scene_min_ade``'s.
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
    energy: np.ndarray | None = None
    scene_min_ade: np.ndarray | None = None
    scene_min_fde: np.ndarray | None = None

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


def energy_score(samples: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """The unbiased sample estimate of the energy score ``ES = E‖X − y‖ − ½ E‖X − X'‖`` (Gneiting & Raftery 2007)
    of each row's samples against its truth, ``‖·‖`` the Euclidean norm over all ``D`` coordinates:
    ``(1/K) Σ_k ‖X_k − y‖ − 1/(2K(K − 1)) Σ_{k≠l} ‖X_k − X_l‖``, whose expectation over the samples is ``ES``.

    Args:
        samples: ``(M, K, D)`` ``K >= 2`` draws per row (a pedestrian's 12 future positions flattened: ``D = 24``,
            metres).
        truth: ``(M, D)`` the true values.

    Returns:
        ``(M,)`` float64 scores, in the units of the inputs.
    """
    x, y = samples.double(), truth.double()
    k = x.shape[1]
    if k < 2:
        raise ValueError(f"the energy score needs at least 2 samples per row, got {k}")
    to_truth = (x - y[:, None]).norm(dim=-1).mean(1)
    between = torch.cdist(x, x).sum((1, 2)) / (k * (k - 1))  # the diagonal is 0: the sum is over k != l
    return to_truth - 0.5 * between


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
    ``sample`` and ``samples > 0``, the best-of-``samples`` ADE/FDE (per pedestrian, over its own samples), the
    per-scene best-of-``samples`` sums of each window (sample ``k`` of every scored pedestrian of the window together)
    and, with ``samples >= 2``, each pedestrian's energy score over its 12-step future (:func:`energy_score`).

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
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("error", "speed", "window", "sigma", "rho", "ade", "fde", "energy")
    }
    scene = np.zeros((2, len(windows))) if samples and sample is not None else None
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
            truth_t = torch.from_numpy(truth).double()
            d = (sampled.double() - truth_t[:, None]).norm(dim=-1)  # (B, K, P, N)
            ade, fde = d.mean(2), d[:, :, -1]  # (B, K, N)
            parts["ade"].append(ade.min(1).values.numpy()[b_idx, n_idx])
            parts["fde"].append(fde.min(1).values.numpy()[b_idx, n_idx])
            s = torch.from_numpy(scored).double()[:, None]  # (B, 1, N)
            assert scene is not None
            scene[0, chunk] = (ade * s).sum(-1).min(1).values.numpy()
            scene[1, chunk] = (fde * s).sum(-1).min(1).values.numpy()
            if samples >= 2:
                bt, nt = torch.from_numpy(b_idx), torch.from_numpy(n_idx)
                rows_k = sampled.double()[bt, :, :, nt]  # (M, K, P, 2): advanced indices come first
                flat = rows_k.reshape(len(b_idx), samples, -1)
                parts["energy"].append(energy_score(flat, truth_t[bt, :, nt].reshape(len(b_idx), -1)).numpy())
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
        cat("energy"),
        None if scene is None else scene[0],
        None if scene is None else scene[1],
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


#: Metrics of a distribution (:func:`distribution_metrics`), each with a ``_ci`` interval: the NLL, the best-of-K
#: ADE/FDE per pedestrian (``min_*``) and per scene (``scene_min_*``), the energy score, and the calibrated coverage
#: of the 90 % regions (added by :func:`crowdnav_mesrnn.evaluation.protocol.evaluate_model`, which calibrates).
DISTRIBUTION_KEYS = ("nll_m", "min_ade_m", "min_fde_m", "scene_min_ade_m", "scene_min_fde_m", "energy_m", "coverage_90")


def distribution_metrics(
    scored: ScoredForecasts, block_len: int = 20, n_resamples: int = 10_000
) -> tuple[dict[str, float], dict[str, PairedErrors]]:
    """NLL (nats per position, metres, averaged over every scored pedestrian and step), best-of-K ADE/FDE per
    pedestrian and per scene and the energy score (metres, averaged over every scored pedestrian) of one split,
    whichever ``scored`` holds, each with its block-bootstrap interval (``KEY_ci``), and the per-window
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
    if scored.scene_min_ade is not None and scored.scene_min_fde is not None:
        sums["scene_min_ade_m"] = PairedErrors(scored.scene_min_ade[keep], counts[keep])
        sums["scene_min_fde_m"] = PairedErrors(scored.scene_min_fde[keep], counts[keep])
    if scored.energy is not None:
        sums["energy_m"] = PairedErrors(scored.window_sums(scored.energy)[keep], counts[keep])
    out: dict[str, float] = {}
    for key, e in sums.items():
        out[key] = e.estimate
        out[f"{key}_ci"] = list(block_bootstrap_ci(e, block_len, n_resamples))  # type: ignore[assignment]
    return out, sums
