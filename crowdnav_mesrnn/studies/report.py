"""``docs/results/predictors.md`` and its JSON: per-split ADE/FDE of every predictor, seeds, paired differences
with block-bootstrap intervals, and the verdicts read from them (``crowdnav-mesrnn predictor report``).

Everything in the page is computed by :func:`build_report` from the shipped checkpoints, the runs of
the comparison plan (``configs/predictor/candidates.yaml``) and, where given, extra checkpoints; the page is
rendered from the JSON by :mod:`crowdnav_mesrnn.studies.report_render` (``--render-only`` re-renders it).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.evaluation.protocol import evaluate_model
from crowdnav_mesrnn.evaluation.statistics import (
    DEFAULT_BLOCK_LEN,
    DEFAULT_RESAMPLES,
    SeededDifference,
    SeededErrors,
    seeded_average_ci,
    seeded_difference_ci,
    verdict,
)
from crowdnav_mesrnn.models.learned import load_predictor
from crowdnav_mesrnn.studies.report_render import NAMES, render, render_plan

#: Paired differences reported with intervals (A − B; negative = A better).
PAIRS: tuple[tuple[str, str], ...] = (
    ("mesrnn", "cv"),
    ("srnn", "cv"),
    ("vlstm", "cv"),
    ("mesrnn", "srnn"),
    ("srnn", "vlstm"),
)


# ------------------------------------------------------------------ computing
#: Per-window errors of one model on one split (:func:`crowdnav_mesrnn.evaluation.metrics.window_errors`), or a
#: list of them, one per training seed.
WindowErrors = dict[str, np.ndarray] | list[dict[str, np.ndarray]]


def _seeded(errs: WindowErrors, metric: str) -> SeededErrors:
    runs = errs if isinstance(errs, list) else [errs]
    counts = [r["pedestrians"] for r in runs]
    if any(not np.array_equal(c, counts[0]) for c in counts):
        raise ValueError("seeds of one model were evaluated on different windows")
    return SeededErrors(np.stack([r[metric] for r in runs]), counts[0])


def compare(
    errors: dict[str, dict[str, WindowErrors]],
    pairs: tuple[tuple[str, str], ...] = PAIRS,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> dict[str, Any]:
    """Paired ADE/FDE differences ``A − B`` per split and over the five-split average, with
    block-bootstrap intervals and verdicts, from per-window errors ``model -> split -> window_errors``.

    A value may be a list of per-window errors, one per training seed: the difference is then between
    seed-averaged errors and the interval also counts the seeds' variance
    (:func:`~crowdnav_mesrnn.evaluation.statistics.seeded_difference_ci`). With one seed per model this is exactly the
    block bootstrap of the paired difference."""
    out: dict[str, Any] = {}
    for a, b in pairs:
        if a not in errors or b not in errors:
            continue
        splits = [s for s in SPLITS if s in errors[a] and s in errors[b]]
        entry: dict[str, Any] = {}
        for metric in ("ade_m", "fde_m"):
            per: dict[str, Any] = {}
            paired: dict[str, tuple[SeededErrors, SeededErrors]] = {}
            for s in splits:
                ea, eb = _seeded(errors[a][s], metric), _seeded(errors[b][s], metric)
                if not np.array_equal(ea.count, eb.count):
                    raise ValueError(f"{a} and {b} were evaluated on different windows of {s}")
                paired[s] = (ea, eb)
                d = seeded_difference_ci(ea, eb, block_len, n_resamples, confidence, seed)
                per[s] = _entry(d, a, b) | {"seeds": [ea.seeds, eb.seeds]}
            if len(paired) == len(SPLITS):
                d = seeded_average_ci(list(paired.values()), block_len, n_resamples, confidence, seed)
                per["average"] = _entry(d, a, b)
            entry[metric] = per
        out[f"{a}-{b}"] = entry
    return out


def _entry(d: SeededDifference, a: str, b: str) -> dict[str, Any]:
    return {
        "diff": d.estimate,
        "ci": list(d.interval),
        "verdict": _verdict(d.interval, a, b),
        "window_se": d.window_se,
        "seed_se": d.seed_se,
        "df": d.df if np.isfinite(d.df) else None,
    }


def _verdict(ci: tuple[float, float], a: str, b: str) -> str:
    v = verdict(ci)
    return {"A better": f"{NAMES[a]} better", "B better": f"{NAMES[b]} better"}.get(v, v)


def seed_results(
    plan_path: str | os.PathLike[str],
    data_dir: str | os.PathLike[str] | None = None,
    cv_errors: dict[str, dict[str, np.ndarray]] | None = None,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
) -> dict[str, Any]:
    """Test ADE/FDE of every finished seed of the plan's selected candidates; mean ± std over seeds;
    and, where every seed of a (model, split) has finished, the paired differences of seed-averaged
    errors with intervals over windows and seeds (against ``cv_errors``, constant velocity's, if given)."""
    from crowdnav_mesrnn.studies.plan import load_plan, run_dir, summary

    plan = load_plan(plan_path)
    rows = summary(plan)
    complete: dict[str, dict[str, WindowErrors]] = {}

    def test_errors(model: str, split: str, checkpoint: str) -> tuple[dict[str, float], dict[str, np.ndarray]]:
        window_sums: dict[str, dict[str, np.ndarray]] = {}
        res = evaluate_model(
            model,
            [split],
            data_dir=data_dir,
            checkpoint_for=lambda s: load_predictor(checkpoint, model, s),
            window_sums=window_sums,
        )
        return {m: res["splits"][split][m] for m in ("ade_m", "fde_m")}, window_sums[split]

    for key, row in rows.items():
        model, split = key.split("/")
        runs = []
        for info in row["seeds"].values():
            info["test"], errs = test_errors(model, split, info["checkpoint"])
            runs.append(errs)
        if row["seeds"]:
            row["test"] = _mean_std([info["test"] for info in row["seeds"].values()])
        if len(row["seeds"]) == len(plan.seeds):
            complete.setdefault(model, {})[split] = runs
        # Every finished candidate on test, for orientation only (the choice above used validation ADE).
        row["candidates_test"] = {}
        for name in row["candidates_val_ade_m"]:  # the finished candidates
            if name == row["selected"] and plan.selection_seed in row["seeds"]:
                row["candidates_test"][name] = row["seeds"][plan.selection_seed]["test"]
                continue
            folder = run_dir(plan, model, split, name, plan.selection_seed)
            row["candidates_test"][name] = test_errors(model, split, str(folder / "best.pt"))[0]
    average: dict[str, Any] = {}
    for model in plan.models if set(plan.splits) == set(SPLITS) else ():
        per_seed = []
        for k in plan.seeds:
            cells = [rows[f"{model}/{s}"]["seeds"].get(k) for s in SPLITS]
            if all(c is not None for c in cells):
                per_seed.append({m: float(np.mean([c["test"][m] for c in cells])) for m in ("ade_m", "fde_m")})
        if per_seed:
            average[model] = _mean_std(per_seed)
    if cv_errors is not None:
        complete["cv"] = dict(cv_errors)
    comparisons = compare(complete, block_len=block_len, n_resamples=n_resamples)
    return {
        "plan": str(plan_path),
        "seeds": list(plan.seeds),
        "export": plan.export,
        "rows": rows,
        "average": average,
        "comparisons": comparisons,
    }


def _mean_std(values: list[dict[str, float]]) -> dict[str, Any]:
    out: dict[str, Any] = {"n": len(values)}
    for m in ("ade_m", "fde_m"):
        x = np.array([v[m] for v in values])
        out[m] = {"mean": float(x.mean()), "std": float(x.std(ddof=1)) if len(x) > 1 else None}
    return out


def build_report(
    extra: dict[str, str] | None = None,
    data_dir: str | os.PathLike[str] | None = None,
    plan: str | os.PathLike[str] | None = None,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
    claims: bool = True,
) -> tuple[str, dict[str, Any]]:
    """Evaluate CV and the shipped VLSTM, SRNN, MESRNN on every split; ``extra`` maps a row label
    ``"<model>:<label>"`` to a checkpoint template with ``{split}`` (rows only for existing files);
    ``plan`` adds the seeds of the comparison plan; ``claims`` the test of the paper's further claims
    (:mod:`crowdnav_mesrnn.studies.claims`; over the plan's seeds where they are all finished). Returns the page
    and the JSON results."""
    results: dict[str, Any] = {}
    errors: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for model in ("cv", "vlstm", "srnn", "mesrnn"):
        errors[model] = {}
        results[model] = evaluate_model(model, "all", data_dir=data_dir, window_sums=errors[model])
    for key, template in (extra or {}).items():
        model, _ = key.split(":", 1)
        splits = [s for s in SPLITS if Path(template.format(split=s, model=model)).is_file()]
        if not splits:
            continue
        res = evaluate_model(
            model,
            splits,
            data_dir=data_dir,
            checkpoint_for=lambda s, m=model, t=template: load_predictor(t.format(split=s, model=m), m, s),
        )
        res["template"] = template
        res["trained_by"] = _training_command(Path(template.format(split=splits[0], model=model)))
        results[key] = res
    results["comparisons"] = compare(errors, block_len=block_len, n_resamples=n_resamples)
    results["bootstrap"] = _bootstrap_info(block_len, n_resamples)
    if plan is not None:
        results["seeds"] = seed_results(plan, data_dir, errors["cv"], block_len, n_resamples)
    if claims:
        from crowdnav_mesrnn.studies.claims.compute import compute_claims

        results["claims"] = compute_claims(data_dir, plan, block_len, n_resamples, headline=results)
    return render(results), results


def add_claims(saved: dict[str, Any], claims: dict[str, Any]) -> dict[str, Any]:
    """The saved results of the main page with their ``claims`` object set to ``claims`` (added or
    replaced); every other key is kept as it was (``predictor report --claims``)."""
    if saved.get("plan_only"):
        raise ValueError("the claims belong on the main page (predictors.md), not on a --plan-only page")
    missing = [k for k in ("cv", "comparisons", "bootstrap") if k not in saved]
    if missing:
        raise ValueError(f"not the results of a predictor report: no {', '.join(missing)}")
    merged = dict(saved)
    merged["claims"] = claims
    return merged


def build_plan_report(
    plan: str | os.PathLike[str],
    data_dir: str | os.PathLike[str] | None = None,
    block_len: int = DEFAULT_BLOCK_LEN,
    n_resamples: int = DEFAULT_RESAMPLES,
) -> tuple[str, dict[str, Any]]:
    """A page for one plan's runs alone (``predictor report --plan-only``): constant velocity and the
    plan's seeds, their differences over seeds and the ordering read from them; no shipped weights.
    For plans that measure without shipping, e.g. ``configs/predictor/fixed_rotation.yaml``."""
    cv: dict[str, dict[str, np.ndarray]] = {}
    results: dict[str, Any] = {
        "plan_only": True,
        "cv": evaluate_model("cv", "all", data_dir=data_dir, window_sums=cv),
        "bootstrap": _bootstrap_info(block_len, n_resamples),
    }
    results["seeds"] = seed_results(plan, data_dir, cv, block_len, n_resamples)
    return render_plan(results), results


def _bootstrap_info(block_len: int, n_resamples: int) -> dict[str, Any]:
    return {
        "method": "moving-block bootstrap over consecutive test windows, percentile interval",
        "block_len_windows": block_len,
        "resamples": n_resamples,
        "confidence": 0.95,
        "seed": 0,
    }


def _training_command(checkpoint: Path) -> str | None:
    """The training command recorded beside a checkpoint (``run.yaml`` of its run folder)."""
    run = checkpoint.parent / "run.yaml"
    if not run.is_file():
        return None
    return (yaml.safe_load(run.read_text()) or {}).get("command")
