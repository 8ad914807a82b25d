"""The claims test: measure every model on every test set, then the rates per bin, the MESRNN − baseline
differences with block-bootstrap intervals, and the verdicts (JSON-ready dicts).

The weights are the comparison plan's seeds where the plan's run folders hold every seed of every
(model, split), else the shipped weights (:func:`weights_for`); the result says which.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import stats as sps

from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.evaluation.metrics import BatchPredictFn, cv_predict_batch
from crowdnav_mesrnn.evaluation.statistics import (
    DEFAULT_BLOCK_LEN,
    DEFAULT_RESAMPLES,
    SeededDifference,
    ratio_differences,
)
from crowdnav_mesrnn.studies.claims.declared import DECLARED, ClaimsConfig
from crowdnav_mesrnn.studies.claims.measure import MOTIONS, bin_label, density_bin, measure_windows

MODELS: tuple[str, ...] = ("cv", "vlstm", "srnn", "mesrnn")
LEARNED: tuple[str, ...] = ("vlstm", "srnn", "mesrnn")
POOLED = "pooled"
#: How the claims section is produced (the page names it).
COMMAND = "crowdnav-mesrnn predictor report --claims --out docs/results/predictors.md"

#: ``model -> split -> [measurements of each seed]`` (:func:`~crowdnav_mesrnn.studies.claims.measure.measure_windows`).
Measured = dict[str, dict[str, list[dict[str, np.ndarray]]]]


# ------------------------------------------------------------------ which weights
def weights_for(plan: str | os.PathLike[str] | None) -> tuple[dict[str, dict[str, list[str]]] | None, str]:
    """The plan's seed checkpoints ``model -> split -> [paths]`` if ``plan`` is given and its run folders
    hold every seed of every (learned model, split), else None (use the shipped weights); and a sentence
    saying which and why."""
    if plan is None:
        return None, "the shipped weights (one seed per model and split): the report was run without a plan"
    from crowdnav_mesrnn.studies.plan import load_plan, summary

    p = load_plan(plan)
    rows = summary(p)
    out: dict[str, dict[str, list[str]]] = {}
    missing = []
    for model in LEARNED:
        for split in SPLITS:
            row = rows.get(f"{model}/{split}")
            if row is None or len(row["seeds"]) != len(p.seeds):
                missing.append(f"{model}/{split}")
                continue
            out.setdefault(model, {})[split] = [row["seeds"][k]["checkpoint"] for k in p.seeds]
    if missing:
        return None, (
            f"the shipped weights (one seed per model and split): the run folders of plan `{plan}` do not hold "
            f"every seed of {len(missing)} of {len(LEARNED) * len(SPLITS)} (model, split) pairs"
        )
    return out, f"seeds {list(p.seeds)} of plan `{plan}` for every learned model and split (differences over seeds)"


def _predictors(model: str, split: str, seeds: dict[str, dict[str, list[str]]] | None) -> list[BatchPredictFn]:
    if model == "cv":
        return [cv_predict_batch]
    if seeds is None:
        from crowdnav_mesrnn.models.pretrained import load_pretrained

        return [load_pretrained(model, split).predict_batch]
    from crowdnav_mesrnn.models.learned import load_predictor

    return [load_predictor(path, model, split).predict_batch for path in seeds[model][split]]


def measure_all(
    data_dir: str | os.PathLike[str] | None = None,
    seeds: dict[str, dict[str, list[str]]] | None = None,
    cfg: ClaimsConfig = DECLARED,
    splits: Sequence[str] = SPLITS,
    log: Callable[[str], None] = print,
) -> Measured:
    """Roll out every model (each seed) on every split's test windows (at least 2 scored pedestrians)
    and measure them."""
    from crowdnav_mesrnn.data.windows import split_windows

    out: Measured = {m: {} for m in MODELS}
    for split in splits:
        windows = split_windows(split, "test", min_scored=2, data_dir=data_dir)
        for model in MODELS:
            out[model][split] = [measure_windows(p, windows, cfg) for p in _predictors(model, split, seeds)]
        log(f"claims: measured {split} ({len(windows)} windows)")
    return out


# ------------------------------------------------------------------ statistics
def _reading(ci: tuple[float, float] | None) -> str:
    if ci is None:
        return "no interval"
    lo, hi = ci
    if hi < 0:
        return "negative"
    if lo > 0:
        return "positive"
    return "no detectable difference"


def _entry(d: SeededDifference, empty: float, weight: float, cfg: ClaimsConfig) -> dict[str, Any] | None:
    """A difference cell, or None when it has fewer than ``cfg.min_cell_count`` pedestrians (pairs)."""
    if not weight >= cfg.min_cell_count or not math.isfinite(d.estimate):
        return None
    ok = empty <= cfg.max_empty_resamples and all(math.isfinite(x) for x in d.interval)
    ci = [float(d.interval[0]), float(d.interval[1])] if ok else None
    return {
        "diff": float(d.estimate),
        "ci": ci,
        "reading": _reading(ci),
        "weight": float(weight),
        "empty_resamples": float(empty),
        "window_se": float(d.window_se),
        "seed_se": float(d.seed_se),
        "df": float(d.df) if math.isfinite(d.df) else None,
    }


class _Table:
    """Numerators ``model -> split -> (S, C, W)`` and weights ``split -> (C, W)`` of one family of
    categories (density bins, motion types, collision scopes)."""

    def __init__(self, labels: Sequence[str], num: dict[str, dict[str, np.ndarray]], den: dict[str, np.ndarray]):
        self.labels = list(labels)
        self.num = num
        self.den = den

    def weight(self, splits: Sequence[str]) -> np.ndarray:
        return sum(self.den[s].sum(1) for s in splits)

    def rates(self, model: str, splits: Sequence[str], cfg: ClaimsConfig) -> dict[str, float | None]:
        w = self.weight(splits)
        tot = sum(self.num[model][s].mean(0).sum(1) for s in splits)
        return {
            lab: (float(tot[i] / w[i]) if w[i] >= cfg.min_cell_count else None) for i, lab in enumerate(self.labels)
        }

    def reported(self, splits: Sequence[str], cfg: ClaimsConfig) -> list[int]:
        return [i for i, w in enumerate(self.weight(splits)) if w >= cfg.min_cell_count]

    def differences(
        self,
        a: str,
        b: str | None,
        splits: Sequence[str],
        cfg: ClaimsConfig,
        boot: dict[str, Any],
        contrast: bool = False,
    ) -> dict[str, Any]:
        """Cells ``label -> entry`` of ``a − b`` (``b`` None: ``a`` itself), and ``"contrast"`` (densest −
        sparsest reported category, with ``"bins"``) if asked and at least two are reported."""
        rep = self.reported(splits, cfg)
        pairs = [(rep[-1], rep[0])] if contrast and len(rep) >= 2 else []
        res = ratio_differences(
            [self.num[a][s] for s in splits],
            None if b is None else [self.num[b][s] for s in splits],
            [self.den[s] for s in splits],
            pairs,
            boot["block_len_windows"],
            boot["resamples"],
            boot["confidence"],
            boot["seed"],
        )
        w = self.weight(splits)
        out: dict[str, Any] = {lab: _entry(*res[i], w[i], cfg) for i, lab in enumerate(self.labels)}
        if pairs:
            hi, lo = pairs[0]
            e = _entry(*res[-1], min(w[hi], w[lo]), cfg)
            out["contrast"] = None if e is None else e | {"bins": [self.labels[lo], self.labels[hi]]}
        elif contrast:
            out["contrast"] = None
        return out

    def split_shares(self, cfg: ClaimsConfig) -> dict[str, Any]:
        """Pooled: each split's share of each category's weight, and the split dominating it (if any)."""
        splits = list(self.den)
        w = self.weight(splits)
        out = {}
        for i, lab in enumerate(self.labels):
            shares = {s: (float(self.den[s][i].sum() / w[i]) if w[i] > 0 else 0.0) for s in splits}
            top = max(shares, key=shares.get)
            out[lab] = {
                "shares": shares,
                "dominated_by": top if w[i] > 0 and shares[top] >= cfg.dominance_share else None,
            }
        return out


def _scopes(splits: Sequence[str]) -> dict[str, list[str]]:
    return {**{s: [s] for s in splits}, POOLED: list(splits)}


def _stack(measured: Measured, model: str, split: str, key: str, mask: np.ndarray) -> np.ndarray:
    """``(S, C, W)``: each seed's per-window ``key`` (``(W,)`` or ``(C, W)``) times ``mask`` ``(C, W)``."""
    return np.stack([np.atleast_2d(m[key]) * mask for m in measured[model][split]])


def _truth(measured: Measured, split: str) -> dict[str, np.ndarray]:
    """The ground truth's measurements of a split (identical for every model: checked)."""
    ref = measured["cv"][split][0]
    for model in MODELS:
        for m in measured[model][split]:
            for key in ("pedestrians", "others", "motion_count", "pairs", "gt_collisions"):
                if not np.array_equal(m[key], ref[key]):
                    raise ValueError(f"{model} on {split}: {key} differs from constant velocity's (other windows?)")
    return ref


def tables(measured: Measured, cfg: ClaimsConfig = DECLARED) -> dict[str, _Table]:
    """The density, motion, collision and (per model's own ADE) difficulty tables of ``measured``."""
    splits = list(measured["cv"])
    k = len(cfg.density_bins)
    bins = [bin_label(lo, hi) for lo, hi in cfg.density_bins]
    dens: dict[str, dict[str, np.ndarray]] = {"density": {}, "motion": {}, "collisions": {}, "matched": {}}
    nums: dict[str, dict[str, dict[str, np.ndarray]]] = {t: {m: {} for m in (*MODELS, "truth")} for t in dens}
    for s in splits:
        gt = _truth(measured, s)
        onehot = (density_bin(gt["others"].astype(np.int64), cfg)[None] == np.arange(k)[:, None]).astype(float)
        dense = (gt["others"] >= cfg.dense_min_others).astype(float)
        coll_mask = np.stack([np.ones_like(dense), dense])
        dens["density"][s] = onehot * gt["pedestrians"]
        dens["matched"][s] = dens["density"][s]
        dens["motion"][s] = gt["motion_count"]
        dens["collisions"][s] = coll_mask * gt["pairs"]
        for model in MODELS:
            nums["density"][model][s] = {m: _stack(measured, model, s, m, onehot) for m in ("ade_m", "fde_m")}
            nums["matched"][model][s] = _stack(measured, model, s, "ade_matched_m", onehot)
            nums["motion"][model][s] = {
                m: _stack(measured, model, s, f"motion_{m}", np.ones((len(MOTIONS), 1))) for m in ("ade_m", "fde_m")
            }
            nums["collisions"][model][s] = _stack(measured, model, s, "collisions", coll_mask)
        nums["collisions"]["truth"][s] = (gt["gt_collisions"] * coll_mask)[None]
    out = {}
    for metric in ("ade_m", "fde_m"):
        out[f"density_{metric}"] = _Table(
            bins, {m: {s: nums["density"][m][s][metric] for s in splits} for m in MODELS}, dens["density"]
        )
        out[f"motion_{metric}"] = _Table(
            MOTIONS, {m: {s: nums["motion"][m][s][metric] for s in splits} for m in MODELS}, dens["motion"]
        )
    out["matched"] = _Table(bins, {m: nums["matched"][m] for m in MODELS}, dens["matched"])
    out["collisions"] = _Table(
        ("all", "dense"), {m: nums["collisions"][m] for m in (*MODELS, "truth")}, dens["collisions"]
    )
    return out


# ------------------------------------------------------------------ the claims
def claims_results(
    measured: Measured,
    weights: str,
    cfg: ClaimsConfig = DECLARED,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> dict[str, Any]:
    """The ``claims`` object of the results JSON from per-window measurements (see the module docstring
    of :mod:`crowdnav_mesrnn.studies.claims.declared` for every definition)."""
    boot = {
        "method": "moving-block bootstrap over consecutive test windows (each split independently), percentile "
        "interval; over seeds, a t interval adding the seeds' variance",
        "block_len_windows": block_len,
        "resamples": n_resamples,
        "confidence": 0.95,
        "seed": seed,
    }
    splits = list(measured["cv"])
    scopes = _scopes(splits)
    t = tables(measured, cfg)
    pairs = [("mesrnn", b) for b in cfg.baselines]
    seeds = {m: len(measured[m][splits[0]]) for m in MODELS}

    def family(prefix: str, contrast: bool) -> dict[str, Any]:
        base = t[f"{prefix}_ade_m"]
        out: dict[str, Any] = {
            "labels": base.labels,
            "weights": {
                sc: dict(zip(base.labels, map(int, base.weight(ss)), strict=True)) for sc, ss in scopes.items()
            },
            "pooled_split_shares": base.split_shares(cfg),
            "models": {
                m: {
                    metric: {sc: t[f"{prefix}_{metric}"].rates(m, ss, cfg) for sc, ss in scopes.items()}
                    for metric in ("ade_m", "fde_m")
                }
                for m in MODELS
            },
            "differences": {
                f"{a}-{b}": {
                    metric: {
                        sc: t[f"{prefix}_{metric}"].differences(a, b, ss, cfg, boot, contrast)
                        for sc, ss in scopes.items()
                    }
                    for metric in ("ade_m", "fde_m")
                }
                for a, b in pairs
            },
        }
        return out

    density = family("density", contrast=True)
    density["windows"] = {
        sc: dict(
            zip(
                density["labels"],
                map(int, sum((t["density_ade_m"].den[s] > 0).sum(1) for s in ss)),
                strict=True,
            )
        )
        for sc, ss in scopes.items()
    }
    motion = family("motion", contrast=False)
    coll = t["collisions"]
    collisions: dict[str, Any] = {
        "labels": coll.labels,
        "pairs": {sc: dict(zip(coll.labels, map(int, coll.weight(ss)), strict=True)) for sc, ss in scopes.items()},
        "pooled_split_shares": coll.split_shares(cfg),
        "ground_truth": {sc: coll.rates("truth", ss, cfg) for sc, ss in scopes.items()},
        "models": {m: {sc: coll.rates(m, ss, cfg) for sc, ss in scopes.items()} for m in MODELS},
        "differences": {
            f"{a}-{b}": {sc: coll.differences(a, b, ss, cfg, boot) for sc, ss in scopes.items()} for a, b in pairs
        },
        "against_ground_truth": {
            m: {sc: coll.differences(m, "truth", ss, cfg, boot) for sc, ss in scopes.items()} for m in MODELS
        },
    }
    difficulty = _difficulty(measured, t, splits, cfg, boot)
    results = {
        "command": COMMAND,
        "weights": weights,
        "seeds": seeds,
        "declared": cfg.to_dict(),
        "bootstrap": boot,
        "density": density,
        "motion": motion,
        "collisions": collisions,
        "difficulty": difficulty,
    }
    results["verdicts"] = verdicts(results, cfg)
    return results


def _difficulty(
    measured: Measured, t: dict[str, _Table], splits: Sequence[str], cfg: ClaimsConfig, boot: dict[str, Any]
) -> dict[str, Any]:
    """Claim (c): density and error per scene (12-step and matched-horizon ADE) and, within each scene,
    the densest − sparsest reported bin of each model's own ADE."""
    across: dict[str, Any] = {}
    for s in splits:
        gt = _truth(measured, s)
        peds = gt["pedestrians"].sum()
        row: dict[str, Any] = {
            "mean_others": float((gt["others"] * gt["pedestrians"]).sum() / peds),
            "dense_share": float((gt["pedestrians"] * (gt["others"] >= cfg.dense_min_others)).sum() / peds),
            "pedestrians": int(peds),
            "ucy": s in cfg.ucy_splits,
        }
        for m in MODELS:
            runs = measured[m][s]
            row[m] = {
                "ade_m": float(np.mean([r["ade_m"].sum() for r in runs]) / peds),
                "ade_matched_m": float(np.mean([r["ade_matched_m"].sum() for r in runs]) / peds),
            }
        across[s] = row
    dens = [across[s]["mean_others"] for s in splits]
    spearman = {}
    for m in MODELS:
        for key in ("ade_m", "ade_matched_m"):
            errs = [across[s][m][key] for s in splits]
            if np.ptp(dens) == 0 or np.ptp(errs) == 0:  # undefined for a constant input
                spearman[f"{m}/{key}"] = {"rho": None, "p": None, "n": len(splits)}
                continue
            rho, p = sps.spearmanr(dens, errs)
            spearman[f"{m}/{key}"] = {"rho": float(rho), "p": float(p), "n": len(splits)}
    within = {
        m: {
            metric: {s: t[table].differences(m, None, [s], cfg, boot, contrast=True)["contrast"] for s in splits}
            for metric, table in (("ade_m", "density_ade_m"), ("ade_matched_m", "matched"))
        }
        for m in MODELS
    }
    return {"across": across, "spearman_across_scenes": spearman, "within": within}


# ------------------------------------------------------------------ verdicts
def _overall(per: dict[str, str]) -> str:
    if per and all(v == "holds" for v in per.values()):
        return "holds"
    if any(v == "contradicted" for v in per.values()):
        return "contradicted"
    return "not established"


def verdicts(claims: dict[str, Any], cfg: ClaimsConfig = DECLARED) -> dict[str, Any]:
    """Each claim's verdict, read from the intervals by the declared rules (``cfg.verdict_rules``)."""
    metric = cfg.primary_metric
    out: dict[str, Any] = {}
    # (a) density: the densest reported pooled bin and the contrast, against each baseline.
    per: dict[str, str] = {}
    for key, entry in claims["density"]["differences"].items():
        cells = entry[metric][POOLED]
        reported = [lab for lab in claims["density"]["labels"] if cells.get(lab) is not None]
        dense, contrast = (cells[reported[-1]] if reported else None), cells.get("contrast")
        readings = [(e or {}).get("reading") for e in (dense, contrast)]
        if readings == ["negative", "negative"]:
            per[key] = "holds"
        elif "positive" in readings:
            per[key] = "contradicted"
        else:
            per[key] = "not established"
    out["density"] = {"per_baseline": per, "overall": _overall(per)}
    # (b) near-stationary pedestrians.
    per = {}
    for key, entry in claims["motion"]["differences"].items():
        r = (entry[metric][POOLED].get(MOTIONS[0]) or {}).get("reading")
        per[key] = {"negative": "holds", "positive": "contradicted"}.get(r, "not established")
    out["motion"] = {"per_baseline": per, "overall": _overall(per)}
    # (a') social compliance in dense windows.
    per = {}
    for key, entry in claims["collisions"]["differences"].items():
        r = (entry[POOLED].get("dense") or {}).get("reading")
        per[key] = {"negative": "holds", "positive": "contradicted"}.get(r, "not established")
    out["collisions"] = {"per_baseline": per, "overall": _overall(per)}
    # (c) difficulty.
    d = claims["difficulty"]
    ucy = [s for s, r in d["across"].items() if r["ucy"]]
    eth = [s for s, r in d["across"].items() if not r["ucy"]]
    denser = min(d["across"][s]["mean_others"] for s in ucy) > max(d["across"][s]["mean_others"] for s in eth)
    cv = {s: d["across"][s]["cv"]["ade_matched_m"] for s in d["across"]}
    harder = min(cv[s] for s in ucy) > max(cv[s] for s in eth)
    within = d["within"]["cv"]["ade_m"]
    reported = {s: e for s, e in within.items() if e is not None}
    grows = bool(reported) and all(e["reading"] == "positive" for e in reported.values())
    parts = {"ucy_denser": denser, "ucy_harder": harder, "error_grows_with_density_within_scenes": grows}
    overall = "holds" if all(parts.values()) else ("contradicted" if not harder else "not established")
    out["difficulty"] = {"parts": parts, "overall": overall}
    return out


def check_headline(measured: Measured, results: dict[str, Any], tol_m: float = 1e-6) -> None:
    """Raise if a model's 12-step ADE per split, from the claims' measurements (one seed: the shipped
    weights), differs from the page's headline figure: the claims must be measured on the same windows
    with the same weights as the rest of the page."""
    for model in MODELS:
        for split, runs in measured[model].items():
            saved = ((results.get(model) or {}).get("splits") or {}).get(split)
            if saved is None or len(runs) != 1:
                continue
            ade = float(runs[0]["ade_m"].sum() / runs[0]["pedestrians"].sum())
            if abs(ade - saved["ade_m"]) > tol_m:
                raise ValueError(
                    f"claims: {model} on {split} gives ADE {ade:.6f} m but the page says {saved['ade_m']:.6f} m: "
                    "the page was made with other weights or data; re-run the whole report"
                )


def compute_claims(
    data_dir: str | os.PathLike[str] | None = None,
    plan: str | os.PathLike[str] | None = None,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    headline: dict[str, Any] | None = None,
    cfg: ClaimsConfig = DECLARED,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Measure and test every claim: the plan's seeds where its run folders hold them all, else the
    shipped weights (:func:`weights_for`). ``headline``: the page's results, whose shipped ADE the
    measurements must reproduce when they use the shipped weights (:func:`check_headline`)."""
    seeds, weights = weights_for(plan)
    log(f"claims: using {weights}")
    measured = measure_all(data_dir, seeds, cfg, log=log)
    checked = seeds is None and headline is not None
    if checked:
        check_headline(measured, headline)
    return claims_results(measured, weights, cfg, block_len, n_resamples) | {"headline_checked": checked}
