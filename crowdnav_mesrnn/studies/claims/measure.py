"""Per-window measurements for the claims test: density, motion type of the true future, errors per
motion type, and colliding pairs of forecasts and of the ground truth (definitions in
:mod:`crowdnav_mesrnn.studies.claims.declared`).

Everything is summed per window (never averaged), so a split's figure is a ratio of sums and blocks of
windows can be resampled by :mod:`crowdnav_mesrnn.evaluation.statistics`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from crowdnav_mesrnn.data.constants import OBS_LEN, STEP_S
from crowdnav_mesrnn.data.windows import Window
from crowdnav_mesrnn.evaluation.metrics import BatchPredictFn, predicted_batches
from crowdnav_mesrnn.studies.claims.declared import DECLARED, ClaimsConfig

#: Motion types of the true future, in the order of the ``motion_*`` rows.
MOTIONS: tuple[str, ...] = ("near-stationary", "linear", "non-linear")

#: Keys of :func:`measure_windows`' result that depend on the forecast; the others are the ground truth's.
FORECAST_KEYS: tuple[str, ...] = ("ade_m", "fde_m", "ade_matched_m", "motion_ade_m", "motion_fde_m", "collisions")


def density_bin(others: np.ndarray, cfg: ClaimsConfig = DECLARED) -> np.ndarray:
    """Index into ``cfg.density_bins`` of each count of other pedestrians (``-1``: in no bin).

    Args:
        others: ``(...)`` integer counts of other pedestrians present at the last observed step.
    """
    out = np.full(np.shape(others), -1, dtype=np.int64)
    for i, (lo, hi) in enumerate(cfg.density_bins):
        inside = (others >= lo) & (others <= (hi if hi is not None else np.iinfo(np.int64).max))
        out[inside & (out < 0)] = i
    return out


def bin_label(lo: int, hi: int | None) -> str:
    """``"1–2"``, ``"11+"``."""
    return f"{lo}+" if hi is None else (f"{lo}" if lo == hi else f"{lo}–{hi}")


def motion_types(
    last_obs: np.ndarray, future: np.ndarray, step_s: np.ndarray, cfg: ClaimsConfig = DECLARED
) -> np.ndarray:
    """Motion type of each true future: 0 near-stationary, 1 linear, 2 non-linear (:data:`MOTIONS`).

    Args:
        last_obs: ``(B, N, 2)`` metres, the position at the last observed step.
        future: ``(B, P, N, 2)`` metres, the true future positions.
        step_s: ``(B,)`` seconds per annotation step of each window's recording.

    Returns:
        ``(B, N)`` int64 (meaningful only for pedestrians present throughout).
    """
    d = np.asarray(future, float) - np.asarray(last_obs, float)[:, None]  # (B, P, N, 2) offsets
    p = d.shape[1]
    k = np.arange(1, p + 1, dtype=float)[None, :, None, None]
    speed = np.linalg.norm(d[:, -1], axis=-1) / (p * np.asarray(step_s, float)[:, None])  # (B, N) m/s
    v = (k * d).sum(1) / (k * k).sum()  # least-squares constant velocity from the last observed position
    residual = np.linalg.norm(d - k * v[:, None], axis=-1).mean(1)  # (B, N) metres
    out = np.full(speed.shape, 2, dtype=np.int64)
    out[residual < cfg.linear_residual_m] = 1
    out[speed < cfg.stationary_speed_mps] = 0
    return out


def colliding_pairs(traj: np.ndarray, scored: np.ndarray, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of scored pedestrians whose trajectories come closer than ``distance_m`` at any step.

    Args:
        traj: ``(B, P, N, 2)`` metres (forecast or ground truth).
        scored: ``(B, N)`` bool.

    Returns:
        ``(collisions, pairs)``: ``(B,)`` int64 numbers of colliding pairs and of pairs of scored pedestrians.
    """
    traj = np.asarray(traj, float)
    diff = traj[:, :, :, None] - traj[:, :, None, :]  # (B, P, N, N, 2)
    closest = np.linalg.norm(diff, axis=-1).min(1)  # (B, N, N)
    n = scored.shape[1]
    both = scored[:, :, None] & scored[:, None, :] & np.triu(np.ones((n, n), bool), 1)[None]
    return (both & (closest < distance_m)).sum((1, 2)), both.sum((1, 2))


def measure_batch(
    positions: np.ndarray,
    present: np.ndarray,
    scored: np.ndarray,
    pred: np.ndarray,
    step_s: np.ndarray,
    cfg: ClaimsConfig = DECLARED,
) -> dict[str, np.ndarray]:
    """Claims measurements of a batch of windows.

    Args:
        positions: ``(B, T, N, 2)`` metres, ``T = OBS_LEN + P``; present ``(B, T, N)``; scored ``(B, N)``.
        pred: ``(B, P, N, 2)`` metres, the forecast.
        step_s: ``(B,)`` seconds per annotation step.

    Returns:
        Per window ``(B,)``: ``pedestrians`` (scored), ``others`` (other pedestrians at the last observed
        step), ``ade_m``/``fde_m`` (sums over scored pedestrians), ``ade_matched_m`` (sum of each one's mean
        error over the steps within ``cfg.matched_horizon_s``), ``collisions``/``gt_collisions``/``pairs``;
        per motion type and window ``(3, B)``: ``motion_count``, ``motion_ade_m``, ``motion_fde_m``.
    """
    positions = np.asarray(positions, float)
    pred = np.asarray(pred, float)
    scored = np.asarray(scored, bool)
    future = positions[:, OBS_LEN:]
    p = future.shape[1]
    err = np.linalg.norm(pred - future, axis=-1)  # (B, P, N)
    s = scored.astype(float)
    ade, fde = err.mean(1), err[:, -1]  # (B, N)
    within = np.arange(1, p + 1)[None, :] * np.asarray(step_s, float)[:, None] <= cfg.matched_horizon_s + 1e-6
    ade_matched = (err * within[:, :, None]).sum(1) / np.maximum(within.sum(1), 1)[:, None]
    kind = motion_types(positions[:, OBS_LEN - 1], future, step_s, cfg)
    onehot = np.stack([(kind == m) & scored for m in range(len(MOTIONS))]).astype(float)  # (3, B, N)
    coll, pairs = colliding_pairs(pred, scored, cfg.collision_distance_m)
    gt_coll, _ = colliding_pairs(future, scored, cfg.collision_distance_m)
    return {
        "pedestrians": scored.sum(1),
        "others": np.asarray(present)[:, OBS_LEN - 1].sum(1) - 1,
        "ade_m": (ade * s).sum(1),
        "fde_m": (fde * s).sum(1),
        "ade_matched_m": (ade_matched * s).sum(1),
        "motion_count": onehot.sum(2),
        "motion_ade_m": (onehot * ade[None]).sum(2),
        "motion_fde_m": (onehot * fde[None]).sum(2),
        "collisions": coll,
        "pairs": pairs,
        "gt_collisions": gt_coll,
    }


def measure_windows(
    predict: BatchPredictFn, windows: Sequence[Window], cfg: ClaimsConfig = DECLARED, batch_size: int = 64
) -> dict[str, np.ndarray]:
    """:func:`measure_batch` of every window, in the order of ``windows`` (time order for a split):
    ``(W,)`` or ``(3, W)`` arrays."""
    if not windows:
        raise ValueError("no windows to measure")
    out: dict[str, np.ndarray] = {}
    for chunk, pos, pres, scored, pred in predicted_batches(predict, windows, batch_size):
        step = np.array([STEP_S[windows[i].recording] for i in chunk])
        part = measure_batch(pos.numpy(), pres.numpy(), scored, pred.float().numpy(), step, cfg)
        for key, value in part.items():
            if key not in out:
                out[key] = np.zeros((*value.shape[:-1], len(windows)), dtype=np.float64)
            out[key][..., chunk] = value
    return out
