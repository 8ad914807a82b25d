"""Fit ``cv_gaussian``'s scale ``σ_h = a + b·h`` per leave-one-out split, select its form on validation, ship JSON.

``python -m crowdnav_mesrnn.models.cv_gaussian_fit --split all --out-dir crowdnav_mesrnn/pretrained`` writes
``cv_gaussian_<split>.json`` (atomically) for each split and prints every candidate's validation NLL.

**Data** (the project's training protocol, :class:`crowdnav_mesrnn.training.Trainer`). Fitting reads the split's
``train`` windows, selection its ``val`` windows (:func:`crowdnav_mesrnn.data.windows.split_windows`: the
``_train``/``_val`` pieces of every recording but the held-out scene's, which is never read), both with at least
:data:`MIN_SCORED` scored pedestrians per window. Every scored pedestrian (present in all 20 frames) contributes its
12 future positions; the error is the constant-velocity forecast minus the truth, in metres.

**Objective.** The mean negative log-likelihood per position of the 2-D isotropic Gaussian,
``log 2π + 2 log σ_h + |e|² / (2σ_h²)`` (nats, densities per m²): the project's NLL (:func:`gaussian.nll` with equal
scales and no correlation). It depends on the data only through the number of positions ``n_h`` and the sum of
squared errors ``S_h`` at each step (:class:`StepStats`), so a fit is a 2-parameter problem on 12 pairs of numbers.

**Method** (scipy). Write ``σ_h = s·(1 − w + w·h)`` with ``s = a + b > 0`` and ``w = b / (a + b) ∈ [0, 1]``, a
one-to-one map of the allowed ``(a, b)``; ``w = 0`` is the form ``a``, ``w = 1`` the form ``b·h``. For a given ``w``
the likelihood's maximum over ``s`` has a closed form, ``s² = Σ (S_h / g_h²) / (2 Σ n_h)`` with ``g_h = 1 − w + w·h``
(:func:`best_scale`), so the one-parameter forms are fitted in closed form (``a² = Σ S_h / (2 Σ n_h)``,
``b² = Σ (S_h / h²) / (2 Σ n_h)``) and ``a + b·h`` by minimising the profile NLL over ``w``: a grid of
:data:`PROFILE_GRID` points over [0, 1] brackets the minimum, which ``scipy.optimize.minimize_scalar`` (bounded
Brent) refines. The endpoints are on the grid, so ``a + b·h`` is never worse than either one-parameter form on the
training data.

**Selection rule** (declared here before any fit on the ETH/UCY data was run). The candidates are ``a + b·h``,
``b·h`` and ``a``, each fitted on the training windows. The kept form is the one with the lowest validation NLL,
except that the two-parameter form gives way to the better one-parameter form when that one's validation NLL is
within :data:`SELECTION_TOLERANCE_NATS` (1e-3 nats per position) of it: a nested form fitted on tens of thousands of
positions beats the form it contains on validation by about 1e-5 nats from noise alone, so a smaller gain is no
evidence for the extra parameter. The rule is applied per split; the test scene plays no part.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from scipy import optimize

from crowdnav_mesrnn.data.constants import PRED_LEN, SPLIT_TEST_RECORDINGS, SPLITS, check_split
from crowdnav_mesrnn.data.paths import DATA_DIR_HELP, find_data_dir
from crowdnav_mesrnn.data.recordings import load_split
from crowdnav_mesrnn.data.windows import Window, split_windows
from crowdnav_mesrnn.evaluation.metrics import collect_forecasts
from crowdnav_mesrnn.models.cv_gaussian import (
    FORMS,
    NAME,
    PARAMS_DIR,
    PARAMS_FORMAT,
    cv_mean_batch,
    params_path,
    validate_record,
)
from crowdnav_mesrnn.models.gaussian import LOG_2PI
from crowdnav_mesrnn.utils import atomic_write_json, code_version, file_sha256

#: Scored pedestrians a window needs (as :attr:`TrainConfig.min_scored` and the trainer's validation windows).
MIN_SCORED: Final[int] = 2
#: How much lower (nats per position) the two-parameter form's validation NLL must be than the better
#: one-parameter form's for it to be kept (the selection rule of the module docstring).
SELECTION_TOLERANCE_NATS: Final[float] = 1e-3
#: Points of the grid over ``w = b / (a + b)`` in [0, 1] that brackets the profile likelihood's minimum.
PROFILE_GRID: Final[int] = 201
#: The selection rule in words, recorded in every parameter file.
SELECTION_RULE: Final[str] = (
    "lowest validation NLL (nats per position, metres) among a+b*h, b*h and a, each fitted on the training windows; "
    f"a+b*h gives way to the better one-parameter form when that is within {SELECTION_TOLERANCE_NATS:g} nats of it"
)
#: The fitting method in words, recorded in every parameter file.
FIT_METHOD: Final[str] = (
    "maximum likelihood of the 2-D isotropic Gaussian N(cv_h, (a + b*h)^2 I) over every future step of every scored "
    "pedestrian of the training windows; with sigma_h = s*(1 - w + w*h), s = a + b, w = b/(a + b): s in closed form "
    "for each w, w = 0 (form a) and w = 1 (form b*h) exact, a+b*h by a grid over w in [0, 1] refined with "
    "scipy.optimize.minimize_scalar (bounded Brent)"
)


class FitError(RuntimeError):
    """The optimiser failed, or the data give nothing to fit."""


@dataclass(frozen=True)
class StepStats:
    """What the likelihood of ``σ_h = a + b·h`` reads from a set of forecast errors.

    Attributes:
        counts: ``(P,)`` int64 positions at each horizon step ``h = 1..P``.
        sq_sums: ``(P,)`` float64 sums of squared error lengths ``|e|²`` at each step, m².
        windows: windows the errors come from.
        pedestrians: scored pedestrians (rows) they hold.
    """

    counts: np.ndarray
    sq_sums: np.ndarray
    windows: int = 0
    pedestrians: int = 0

    @classmethod
    def from_errors(cls, error: np.ndarray, windows: int = 0) -> StepStats:
        """From errors ``(M, P, 2)`` metres, every step of every row observed."""
        error = np.asarray(error, dtype=np.float64)
        if error.ndim != 3 or error.shape[-1] != 2:
            raise ValueError(f"errors must have shape (M, P, 2), got {error.shape}")
        m, p, _ = error.shape
        return cls(np.full(p, m, np.int64), (error**2).sum(axis=(0, 2)), windows, m)

    @property
    def positions(self) -> int:
        return int(self.counts.sum())

    def sigma_mle_m(self) -> np.ndarray:
        """``(P,)`` each step's own maximum-likelihood scale ``sqrt(S_h / (2 n_h))``, metres (no form imposed)."""
        return np.sqrt(self.sq_sums / (2.0 * np.maximum(self.counts, 1)))


def window_stats(windows: Sequence[Window]) -> StepStats:
    """The constant-velocity errors of every scored pedestrian of ``windows`` (the project's
    :func:`~crowdnav_mesrnn.evaluation.collect_forecasts`), summarised per step."""
    scored = collect_forecasts(windows, predict=cv_mean_batch)
    return StepStats.from_errors(scored.error, len(windows))


def _steps(stats: StepStats) -> np.ndarray:
    return np.arange(1, len(stats.counts) + 1, dtype=np.float64)


def mean_nll(stats: StepStats, a_m: float, b_m: float) -> float:
    """Mean NLL per position (nats, densities per m²) of the errors under ``N(0, (a + b·h)² I)``."""
    total = stats.positions
    if total == 0:
        raise FitError("no positions: the windows hold no scored pedestrian")
    sigma = a_m + b_m * _steps(stats)
    if np.any(sigma <= 0):
        return math.inf
    n, s = stats.counts, stats.sq_sums
    return float((n * (LOG_2PI + 2.0 * np.log(sigma)) + s / (2.0 * sigma**2)).sum()) / total


def best_scale(stats: StepStats, w: float) -> float:
    """The maximum-likelihood ``s = a + b`` for the share ``w = b / (a + b)`` (``σ_h = s·(1 − w + w·h)``):
    ``s² = Σ (S_h / g_h²) / (2 Σ n_h)`` with ``g_h = 1 − w + w·h``."""
    g = 1.0 - w + w * _steps(stats)
    return math.sqrt(float((stats.sq_sums / g**2).sum()) / (2.0 * stats.positions))


def _profile_nll(stats: StepStats, w: float) -> float:
    s = best_scale(stats, w)
    return mean_nll(stats, s * (1.0 - w), s * w)


def fit_form(stats: StepStats, form: str) -> tuple[float, float]:
    """The maximum-likelihood ``(a_m, b_m)`` of ``form`` (:data:`FORMS`) on ``stats`` (method: module docstring)."""
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; valid: {', '.join(FORMS)}")
    if stats.positions == 0 or not float(stats.sq_sums.sum()) > 0:
        raise FitError("no errors to fit: the windows hold no scored pedestrian, or every forecast is exact")
    if form == "a+b*h":
        grid = np.linspace(0.0, 1.0, PROFILE_GRID)
        values = [_profile_nll(stats, float(w)) for w in grid]
        i = int(np.argmin(values))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        res = optimize.minimize_scalar(
            lambda w: _profile_nll(stats, float(w)), bounds=(lo, hi), method="bounded", options={"xatol": 1e-12}
        )
        if not res.success or not math.isfinite(res.fun):
            raise FitError(f"minimize_scalar did not fit a+b*h: {res.message!r}")
        w = float(res.x) if res.fun < values[i] else float(grid[i])
    else:
        w = 0.0 if form == "a" else 1.0
    s = best_scale(stats, w)
    return s * (1.0 - w), s * w


def select_form(val_nll: Mapping[str, float], tolerance: float = SELECTION_TOLERANCE_NATS) -> str:
    """The form kept by the selection rule (module docstring) from each candidate's validation NLL."""
    for form in FORMS:
        if form not in val_nll or not math.isfinite(val_nll[form]):
            raise ValueError(f"validation NLL of form {form!r} missing or not finite: {val_nll.get(form)!r}")
    best = min(FORMS, key=lambda f: val_nll[f])
    if best == "a+b*h":
        simpler = min(("b*h", "a"), key=lambda f: val_nll[f])
        if val_nll[simpler] <= val_nll[best] + tolerance:
            return simpler
    return best


def fit_candidates(train: StepStats, val: StepStats) -> dict[str, dict[str, float]]:
    """``form -> {a_m, b_m, train_nll, val_nll}`` for every form of :data:`FORMS`."""
    out: dict[str, dict[str, float]] = {}
    for form in FORMS:
        a, b = fit_form(train, form)
        out[form] = {"a_m": a, "b_m": b, "train_nll": mean_nll(train, a, b), "val_nll": mean_nll(val, a, b)}
    return out


def _describe(split: str, part: str, stats: StepStats, data_dir: str | os.PathLike[str] | None) -> dict[str, Any]:
    files = [
        {"file": f"{rec.path.parent.name}/{rec.path.name}", "sha256": file_sha256(rec.path)}
        for rec in load_split(split, part, data_dir)
    ]
    return {
        "part": part,
        "files": files,
        "windows": stats.windows,
        "pedestrians": stats.pedestrians,
        "positions": stats.positions,
        "step_sigma_mle_m": [round(float(s), 6) for s in stats.sigma_mle_m()],
    }


def _check_no_held_out(split: str, windows: Sequence[Window]) -> None:
    held_out = set(SPLIT_TEST_RECORDINGS[split])
    for w in windows:
        base = w.recording.removesuffix("_train").removesuffix("_val")
        if base in held_out or w.recording == base:
            raise FitError(f"split {split!r}: window from {w.recording!r}, not a training/validation piece")


def fit_split(split: str, data_dir: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Fit every candidate on ``split``'s training windows, select on its validation windows (module docstring);
    returns the parameter file's record (validated by :func:`validate_record`)."""
    check_split(split)
    stats: dict[str, StepStats] = {}
    for part in ("train", "val"):
        windows = split_windows(split, part, min_scored=MIN_SCORED, data_dir=data_dir)
        _check_no_held_out(split, windows)
        stats[part] = window_stats(windows)
    candidates = fit_candidates(stats["train"], stats["val"])
    form = select_form({f: c["val_nll"] for f, c in candidates.items()})
    record: dict[str, Any] = {
        "format": PARAMS_FORMAT,
        "model": NAME,
        "split": split,
        "form": form,
        "a_m": candidates[form]["a_m"],
        "b_m": candidates[form]["b_m"],
        "sigma": f"a_m + b_m * h metres at horizon step h = 1..{PRED_LEN} annotation steps, the same in x and y",
        "candidates": candidates,
        "selection": {
            "rule": SELECTION_RULE,
            "tolerance_nats": SELECTION_TOLERANCE_NATS,
            "nll_unit": "nats per position, densities per m^2",
        },
        "fit": {"method": FIT_METHOD, "objective": "mean NLL per position over the training windows"},
        "data": {
            "windows": f"8 observed + 12 future annotation steps, at least {MIN_SCORED} scored pedestrians "
            "(present in all 20 steps); every scored pedestrian's 12 future positions",
            "held_out_never_read": list(SPLIT_TEST_RECORDINGS[split]),
            "train": _describe(split, "train", stats["train"], data_dir),
            "val": _describe(split, "val", stats["val"], data_dir),
        },
        "code_version": code_version(),
    }
    validate_record(record, f"<record of split {split}>", split)
    return record


def write_params(record: Mapping[str, Any], out_dir: str | os.PathLike[str] = PARAMS_DIR) -> Path:
    """Write ``cv_gaussian_<split>.json`` into ``out_dir`` atomically (validated first)."""
    path = params_path(record["split"], out_dir)
    validate_record(dict(record), path, record["split"])
    return atomic_write_json(path, record)


def format_table(records: Sequence[Mapping[str, Any]]) -> str:
    """One row per split: the selected form, ``a``, ``b`` and every candidate's validation NLL."""
    head = f"{'split':<6} {'form':<6} {'a_m':>8} {'b_m':>8} " + " ".join(f"{'val ' + f:>12}" for f in FORMS)
    head += f" {'train pos':>10} {'val pos':>8}"
    rows = [head]
    for r in records:
        c = r["candidates"]
        rows.append(
            f"{r['split']:<6} {r['form']:<6} {r['a_m']:>8.4f} {r['b_m']:>8.4f} "
            + " ".join(f"{c[f]['val_nll']:>12.4f}" for f in FORMS)
            + f" {r['data']['train']['positions']:>10} {r['data']['val']['positions']:>8}"
        )
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    """Fit, select and write the parameter files of the chosen splits; print the table of :func:`format_table`."""
    parser = argparse.ArgumentParser(
        prog="python -m crowdnav_mesrnn.models.cv_gaussian_fit",
        description="Fit cv_gaussian (constant velocity + isotropic Gaussian, sigma = a + b*h) per leave-one-out "
        "split on its training windows, select the form on validation, write cv_gaussian_<split>.json.",
    )
    parser.add_argument("--split", default="all", choices=[*SPLITS, "all"], help="split to fit (default: all)")
    parser.add_argument("--out-dir", default=str(PARAMS_DIR), help=f"where to write the files (default: {PARAMS_DIR})")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    args = parser.parse_args(argv)
    find_data_dir(args.data_dir)  # DataNotFoundError lists where it looked, before any work
    splits = list(SPLITS) if args.split == "all" else [args.split]
    records = []
    for split in splits:
        record = fit_split(split, args.data_dir)
        path = write_params(record, args.out_dir)
        print(f"wrote {path}", file=sys.stderr)
        records.append(record)
    print(format_table(records))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
