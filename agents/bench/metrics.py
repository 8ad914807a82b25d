"""The predictor half of ``crowdnav-mesrnn bench``: ADE/FDE of any predictor on the leave-one-out test windows,
paired with constant velocity on the same windows, with block-bootstrap intervals.

Any predictor name works (shipped, an installed plug-in, an import path): each split's windows are forecast by
``crowdnav_mesrnn.predictors.load(name, split)``, one :meth:`forecast` call per window with every pedestrian
seen in its 8 observed steps, exactly as the environment calls it. Scoring is the project's (pedestrians present
in all 20 frames, windows with at least two of them; :func:`crowdnav_mesrnn.evaluation.window_errors`), so the
shipped models score here as on the results page. Per-window error sums are cached per split in ``out_dir``
keyed by the predictor's fingerprint, so a re-run (or a resumed one) recomputes nothing.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, SPLITS, check_split
from crowdnav_mesrnn.data.windows import Window, split_windows, window_locator
from crowdnav_mesrnn.evaluation.metrics import cv_predict_batch, window_errors
from crowdnav_mesrnn.evaluation.protocol import split_norm
from crowdnav_mesrnn.evaluation.statistics import DEFAULT_BLOCK_LEN, PairedErrors, average_ci, block_bootstrap_ci
from crowdnav_mesrnn.models.base import Predictor
from crowdnav_mesrnn.predictors import check_forecast, label_of
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json

#: Metrics compared against constant velocity.
BENCH_METRICS: tuple[str, ...] = ("ade_m", "fde_m")
#: Test windows need at least this many scored pedestrians (the standard protocol).
MIN_SCORED: int = 2


def protocol_batch_fn(
    model: Predictor, windows: Sequence[Window] = ()
) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """A :data:`~crowdnav_mesrnn.evaluation.BatchPredictFn` calling ``model.forecast`` once per window.

    Each window passes the pedestrians present in any of its first ``OBS_LEN`` steps (``(OBS_LEN, n, 2)`` metres
    and ``(OBS_LEN, n)`` mask); the forecast ``(n, pred_len, 2)`` is scattered back into ``(B, pred_len, N, 2)``.
    Every forecast passes :func:`~crowdnav_mesrnn.predictors.check_forecast` (shape, finite for the pedestrians
    present at the last observed step); its error names the window among ``windows`` (recording and frame).
    """
    locate = window_locator(windows)

    def predict(positions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        pos = positions[:, :OBS_LEN].numpy()
        m = mask[:, :OBS_LEN].numpy().astype(bool)
        b, _, n, _ = pos.shape
        out = np.zeros((b, model.pred_len, n, 2), np.float32)
        for i in range(b):
            seen = np.flatnonzero(m[i].any(axis=0))
            if len(seen) == 0:
                continue
            hist = np.where(m[i][:, seen, None], pos[i][:, seen], 0.0).astype(np.float32)
            now = m[i][-1, seen]  # the rows read (the protocol leaves the others unread)
            pred = check_forecast(
                model.forecast(hist, m[i][:, seen]),
                name=label_of(model),
                expected_shape=(len(seen), model.pred_len, 2),
                rows=now,
                **locate(positions[i].numpy(), mask[i].numpy()),
            )
            out[i][:, seen[now]] = pred[now].transpose(1, 0, 2)
        return torch.from_numpy(out)

    return predict


def predictor_identity(name: str, split: str) -> tuple[Predictor, str]:
    """The loaded predictor for ``split`` and a digest of what determines its forecasts: the forecast cache's key
    (:func:`envs.forecasting.cache.predictor_fingerprint`: weights and, for a plug-in, its identity), or the spec's
    identity for a shipped predictor without weights (constant velocity)."""
    from crowdnav_mesrnn.predictors import load, resolve
    from envs.forecasting.cache import predictor_fingerprint

    model = load(name, split)
    return model, predictor_fingerprint(model) or resolve(name).identity()


def _split_sums(
    name: str, split: str, out_dir: Path | None, data_dir: str | os.PathLike[str] | None, log: Callable[[str], None]
) -> dict[str, np.ndarray]:
    """Per-window sums of the predictor and of constant velocity on ``split``'s test windows (cached)."""
    model, digest = predictor_identity(name, split)
    cache = out_dir / f"windows_{split}.npz" if out_dir is not None else None
    if cache is not None and cache.is_file():
        try:
            with np.load(cache, allow_pickle=False) as z:
                if str(z["identity"]) == digest:
                    log(f"  {split}: reusing {cache}")
                    return {k: z[k] for k in z.files if k != "identity"}
        except (OSError, KeyError, ValueError):
            pass  # unreadable or another predictor's: recompute
    windows = split_windows(split, "test", min_scored=MIN_SCORED, data_dir=data_dir)
    norm = split_norm(split, data_dir)
    ours = window_errors(protocol_batch_fn(model, windows), windows, norm)
    cv = window_errors(cv_predict_batch, windows, norm)
    sums = {"pedestrians": ours["pedestrians"]}
    for k in BENCH_METRICS:
        sums[k] = ours[k]
        sums[f"cv_{k}"] = cv[k]
    if cache is not None:
        atomic_write(cache, lambda fh: np.savez(fh, identity=np.array(digest), **sums))
    log(f"  {split}: {len(windows)} windows forecast")
    return sums


def predictor_metrics(
    name: str,
    splits: Sequence[str] = SPLITS,
    out_dir: str | os.PathLike[str] | None = None,
    data_dir: str | os.PathLike[str] | None = None,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = 10_000,
    seed: int = 0,
    log: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """ADE/FDE of ``name`` and of constant velocity on each split's test windows, and the paired difference
    (``name`` − CV, metres; negative = better than CV) with its block-bootstrap interval; with several splits also
    their unweighted average.

    Returns:
        ``{"predictor", "splits": {split: {"windows", "pedestrians", "ade_m", "fde_m", "cv_ade_m", "cv_fde_m",
        "ade_m_diff", "ade_m_diff_ci", "fde_m_diff", "fde_m_diff_ci"}}, "average": {...}, "block_len",
        "resamples"}`` (the average has the same metric keys).
    """
    for s in splits:
        check_split(s)
    out = Path(out_dir) if out_dir is not None else None
    per_split: dict[str, dict[str, Any]] = {}
    paired: dict[str, dict[str, PairedErrors]] = {k: {} for k in BENCH_METRICS}
    for split in splits:
        sums = _split_sums(name, split, out, data_dir, log)
        count = sums["pedestrians"]
        row: dict[str, Any] = {"windows": len(count), "pedestrians": int(count.sum())}
        for k in BENCH_METRICS:
            row[k] = float(sums[k].sum() / count.sum())
            row[f"cv_{k}"] = float(sums[f"cv_{k}"].sum() / count.sum())
            pe = PairedErrors(sums[k] - sums[f"cv_{k}"], count)
            paired[k][split] = pe
            row[f"{k}_diff"] = pe.estimate
            row[f"{k}_diff_ci"] = list(block_bootstrap_ci(pe, block_len, n_resamples, seed=seed))
        per_split[split] = row
    result: dict[str, Any] = {
        "predictor": name,
        "splits": per_split,
        "block_len": block_len,
        "resamples": n_resamples,
    }
    if len(splits) > 1:
        avg: dict[str, Any] = {}
        for k in BENCH_METRICS:
            avg[k] = float(np.mean([per_split[s][k] for s in splits]))
            avg[f"cv_{k}"] = float(np.mean([per_split[s][f"cv_{k}"] for s in splits]))
            est, ci = average_ci(paired[k], block_len, n_resamples, seed=seed)
            avg[f"{k}_diff"], avg[f"{k}_diff_ci"] = est, list(ci)
        result["average"] = avg
    if out is not None:
        atomic_write_json(out / "predictor_metrics.json", result)
    return result


def load_metrics(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a ``predictor_metrics.json`` written by :func:`predictor_metrics`."""
    return json.loads(Path(path).read_text())
