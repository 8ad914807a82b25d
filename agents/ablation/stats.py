"""The statistics of the summary: crowd-density bins and the pre-declared paired tests."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from agents.ablation.config import OUTCOMES, AblationConfig
from agents.ablation.episodes import _Episodes


def density_edges(cfg: AblationConfig, pooled: Mapping[tuple[str, str], _Episodes]) -> list[float]:
    """Crowd-density bin edges: the configured edges, or quantiles over the fixed episode list of every split,
    rounded to whole pedestrians.

    The episode list is the same in every cell of a split, so each (split, episode) counts once.
    """
    if isinstance(cfg.density_bins, tuple):
        return list(cfg.density_bins)
    per_episode: dict[tuple[str, int], float] = {}
    for eps in pooled.values():
        for (split, _seed, ep), d in zip(eps.keys, eps.metric("crowd_density"), strict=True):
            if math.isfinite(d):
                per_episode.setdefault((split, ep), d)
    if not per_episode:
        return []
    values = np.asarray(list(per_episode.values()))
    edges = np.quantile(values, np.linspace(0.0, 1.0, cfg.density_bins + 1))
    # whole pedestrians: the density counts people, so the bins are read as "1-5 pedestrians" (the outer edges
    # rounded outwards, so every episode stays inside)
    edges = np.concatenate([[np.floor(edges[0])], np.round(edges[1:-1]), [np.ceil(edges[-1])]])
    edges = np.unique(edges)
    return [float(e) for e in edges] if edges.size >= 2 else [float(values.min()), float(values.max())]


def _bin_index(density: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """Bin of each density: ``[e0, e1), [e1, e2), ..., [e_{k-1}, e_k]``; -1 outside."""
    e = np.asarray(edges)
    idx = np.searchsorted(e, density, side="right") - 1
    idx = np.where(density == e[-1], len(e) - 2, idx)
    return np.where((density < e[0]) | (density > e[-1]) | ~np.isfinite(density), -1, idx)


def by_density(episodes: _Episodes, edges: Sequence[float], confidence: float = 0.95) -> list[dict[str, Any]]:
    from agents.stats import wilson_interval

    if len(edges) < 2:
        return []
    idx = _bin_index(episodes.metric("crowd_density"), edges)
    outcome = episodes.outcome()
    rows = []
    for b in range(len(edges) - 1):
        sel = idx == b
        n = int(sel.sum())
        row: dict[str, Any] = {"bin": [edges[b], edges[b + 1]], "episodes": n}
        for o in OUTCOMES:
            k = int(np.sum(outcome[sel] == o))
            row[f"{o}_rate"] = k / n if n else math.nan
            row[f"{o}_ci"] = list(wilson_interval(k, n, confidence))
        rows.append(row)
    return rows


def _pair_up(
    a: _Episodes, b: _Episodes, split: str
) -> tuple[list[tuple[int | None, int]], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of one split keyed by (seed, episode); a side without seeds (a planner) pairs its episode with
    that episode of every seed of the other side. Returns the keys, both sides' success and navigation times."""
    a_idx = {(s, e): i for i, (sp, s, e) in enumerate(a.keys) if sp == split}
    b_idx = {(s, e): i for i, (sp, s, e) in enumerate(b.keys) if sp == split}
    a_seedless = all(s is None for s, _ in a_idx)
    b_seedless = all(s is None for s, _ in b_idx)
    pairs: list[tuple[tuple[int | None, int], int, int]] = []
    if a_seedless == b_seedless:
        pairs = [(k, a_idx[k], b_idx[k]) for k in a_idx.keys() & b_idx.keys()]
    elif b_seedless:
        pairs = [((s, e), i, b_idx[(None, e)]) for (s, e), i in a_idx.items() if (None, e) in b_idx]
    else:
        pairs = [((s, e), a_idx[(None, e)], j) for (s, e), j in b_idx.items() if (None, e) in a_idx]
    pairs.sort(key=lambda p: (-1 if p[0][0] is None else p[0][0], p[0][1]))
    ia = [p[1] for p in pairs]
    ib = [p[2] for p in pairs]
    sa = np.asarray(a.outcome()[ia] == "success", dtype=bool)
    sb = np.asarray(b.outcome()[ib] == "success", dtype=bool)
    ta = a.metric("navigation_time_s")[ia]
    tb = b.metric("navigation_time_s")[ib]
    return [p[0] for p in pairs], sa, sb, ta, tb


def _seed_level(
    a: _Episodes,
    b: _Episodes,
    keys: Sequence[tuple[int | None, int]],
    sa: np.ndarray,
    sb: np.ndarray,
    confidence: float,
) -> dict[str, Any] | None:
    """Welch's t-test on per-seed success rates over the paired episodes (the training seed as the unit);
    a side without seeds (a planner) is one fixed rate. ``None`` when neither side has seeds."""
    from agents.stats import welch_seed_test

    a_seeded = any(s is not None for _, s, _ in a.keys)
    b_seeded = any(s is not None for _, s, _ in b.keys)
    if not (a_seeded or b_seeded):
        return None
    seeds = np.asarray([-1 if s is None else s for s, _ in keys])
    groups = [seeds == s for s in np.unique(seeds)]

    def rates(success: np.ndarray, seeded: bool) -> list[float]:
        per = [float(success[g].mean()) for g in groups]
        return per if seeded else per[:1]  # a seedless side repeats the same episodes for every seed

    ra, rb = rates(sa, a_seeded), rates(sb, b_seeded)
    return {**welch_seed_test(ra, rb, confidence), "rates_a": ra, "rates_b": rb}


def paired_tests(
    cfg: AblationConfig, pooled: Mapping[tuple[str, str], _Episodes]
) -> tuple[list[dict[str, Any]], dict[str, int]]:
    """The declared comparisons: exact McNemar on success and Wilcoxon on navigation time (both succeeded),
    Holm-adjusted within each endpoint over every test performed; returns the tests and the family sizes.

    A success test of episodes that record the metrics added in issue 31 (:data:`agents.rollout.ADDED_METRICS`)
    carries ``difference_exact_ci`` (:func:`agents.stats.mcnemar_difference_ci`) and ``verdict``
    (:func:`agents.stats.paired_verdict` on the Holm-adjusted p); one of an older archive carries the paired bootstrap
    ``difference_ci`` it was first summarised with."""
    from agents.rollout import ADDED_METRICS, recorded_metrics
    from agents.stats import holm, mcnemar_exact, mcnemar_min_detectable_difference, paired_verdict, wilcoxon_paired

    planned: list[tuple[str, str, str, str, str, str]] = []  # (policy_a, arm_a, policy_b, arm_b, split, kind)
    for policy in cfg.policies:
        for a, b in cfg.comparisons:
            if policy.uses(cfg.arm(a)) and policy.uses(cfg.arm(b)):
                planned += [(policy.name, a, policy.name, b, split, "arms") for split in cfg.splits]
    for p, q in cfg.policy_comparisons:
        for arm in cfg.arms:
            if cfg.policy(p).uses(arm) and cfg.policy(q).uses(arm):
                planned += [(p, arm.label, q, arm.label, split, "policies") for split in cfg.splits]
    # The success difference's interval: episodes recorded with the metrics of issue 31 get the exact conditional
    # interval, which excludes 0 exactly when the McNemar test rejects, and a verdict; archives written before keep
    # the paired bootstrap interval they were summarised with (under its own key), so their summaries stay as they are.
    current = bool(set(ADDED_METRICS) & set(recorded_metrics([r for eps in pooled.values() for r in eps.rows])))
    intervals = ("exact",) if current else ("bootstrap",)
    tests: list[dict[str, Any]] = []
    for pa, aa, pb, ab, split, kind in planned:
        base = {"comparison": kind, "split": split, "a": {"policy": pa, "arm": aa}, "b": {"policy": pb, "arm": ab}}
        ea, eb = pooled.get((pa, aa)), pooled.get((pb, ab))
        if ea is None or eb is None:
            tests.append({**base, "endpoint": "success", "missing": True})
            continue
        keys, sa, sb, ta, tb = _pair_up(ea, eb, split)
        if sa.size == 0:
            tests.append({**base, "endpoint": "success", "missing": True})
            continue
        mc = mcnemar_exact(sa, sb, intervals=intervals)
        seed_level = _seed_level(ea, eb, keys, sa, sb, 0.95)
        tests.append({**base, "endpoint": "success", **mc, **({"seed_level": seed_level} if seed_level else {})})
        both = sa & sb
        wx = wilcoxon_paired(ta[both], tb[both])
        tests.append({**base, "endpoint": "navigation_time_s", "population": "episodes both finished", **wx})
    families: dict[str, int] = {}
    for endpoint in ("success", "navigation_time_s"):
        members = [t for t in tests if t["endpoint"] == endpoint and not t.get("missing")]
        families[endpoint] = len(members)
        for t, adj in zip(members, holm([t["p_value"] for t in members]), strict=True):
            t["p_holm"] = adj
            t["family_size"] = len(members)
            t["significant"] = bool(adj <= cfg.alpha)
            if current and endpoint == "success":
                t["verdict"] = paired_verdict(t["difference"], adj, cfg.alpha)
    seed_tests = [t["seed_level"] for t in tests if t.get("seed_level") and math.isfinite(t["seed_level"]["p_value"])]
    families["success_seed_level"] = len(seed_tests)
    for st, adj in zip(seed_tests, holm([st["p_value"] for st in seed_tests]), strict=True):
        st["p_holm"] = adj
        st["family_size"] = len(seed_tests)
        st["significant"] = bool(adj <= cfg.alpha)
    m = max(families.get("success", 0), 1)
    for t in tests:
        if t["endpoint"] == "success" and not t.get("missing"):
            psi = (t["b01"] + t["b10"]) / t["n"]
            t["discordant_fraction"] = psi
            t["mdd"] = mcnemar_min_detectable_difference(t["n"], psi, cfg.alpha, cfg.power)
            t["mdd_holm_strictest"] = mcnemar_min_detectable_difference(t["n"], psi, cfg.alpha / m, cfg.power)
    return tests, families


def _clean(obj: Any) -> Any:
    """JSON-ready: nan/inf become null, tuples lists, numpy scalars Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
