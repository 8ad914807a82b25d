"""ADE/FDE of predictors on the leave-one-out test parts, with a true autoregressive rollout."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS, check_split
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.recordings import load_split
from crowdnav_mesrnn.data.windows import Window, collate, split_windows

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


def split_norm(split: str, data_dir: str | os.PathLike[str] | None = None) -> MinMax:
    """The split's normalisation, fitted on its training part (used for the normalised metric)."""
    return MinMax.fit_recordings(load_split(split, "train", data_dir))


def evaluate_model(
    model: str,
    splits: Sequence[str] | str = "all",
    data_dir: str | os.PathLike[str] | None = None,
    checkpoint_for: Callable[[str], Any] | None = None,
    part: str = "test",
    min_scored: int = 2,
    batch_size: int = 64,
    window_sums: dict[str, dict[str, np.ndarray]] | None = None,
) -> dict[str, Any]:
    """Evaluate ``cv`` or a learned model on each split's ``part``; averaged over the splits.

    Args:
        checkpoint_for: ``split -> LearnedPredictor`` (default: the shipped pretrained weights).
        window_sums: if given, filled with ``split ->`` :func:`window_errors` (windows in time order),
            for paired comparisons.
    """
    if splits == "all":
        splits = SPLITS
    elif isinstance(splits, str):
        splits = [splits]
    for s in splits:
        check_split(s)
    result: dict[str, Any] = {"model": model, "part": part, "splits": {}}
    for split in splits:
        windows = split_windows(split, part, min_scored=min_scored, data_dir=data_dir)
        norm = split_norm(split, data_dir)
        if model == "cv":
            predict: BatchPredictFn = cv_predict_batch
        else:
            if checkpoint_for is None:
                from crowdnav_mesrnn.models.pretrained import load_pretrained

                predictor = load_pretrained(model, split)
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
    if len(splits) > 1:
        result["splits"]["average"] = {
            k: float(np.mean([result["splits"][s][k] for s in splits])) for k in METRIC_KEYS
        } | {
            "windows": sum(result["splits"][s]["windows"] for s in splits),
            "pedestrians": sum(result["splits"][s]["pedestrians"] for s in splits),
        }
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
    return "\n".join(lines)
