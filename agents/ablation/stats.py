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


def by_density(
    episodes: _Episodes, edges: Sequence[float], confidence: float = 0.95, by_episode: bool = False
) -> list[dict[str, Any]]:
    """Outcome rates per crowd-density bin, with Wilson intervals over the rows, or with ``by_episode`` (a seeded
    policy under ``test_unit: episode``) percentile bootstrap intervals resampling episodes, each with all its seeds'
    rows (:func:`agents.ablation.episodes.episode_intervals`; a bin holds whole episodes: the density is the
    episode's, the same for every seed)."""
    from agents.ablation.episodes import _ratio_interval, episode_clusters, resample_weights
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
        if by_episode and n:
            which, n_clusters = episode_clusters([k for k, keep in zip(episodes.keys, sel, strict=True) if keep])
            rows_per = np.bincount(which, minlength=n_clusters).astype(float)
            weights = resample_weights(n_clusters)
        for o in OUTCOMES:
            k = int(np.sum(outcome[sel] == o))
            row[f"{o}_rate"] = k / n if n else math.nan
            if by_episode and n:
                hits = np.bincount(which, weights=(outcome[sel] == o).astype(float), minlength=n_clusters)
                row[f"{o}_ci"] = _ratio_interval(hits, rows_per, weights, confidence)
            else:
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
    a_seeded: bool,
    b_seeded: bool,
    keys: Sequence[tuple[int | None, int]],
    sa: np.ndarray,
    sb: np.ndarray,
    confidence: float,
) -> dict[str, Any] | None:
    """The seed-level test, paired by seed (:func:`agents.stats.paired_seed_test`): each training seed's success rate
    over the paired episodes is one value, seed ``i`` of one side against seed ``i`` of the other; a side without
    seeds (a planner) is one fixed rate on the same episodes, which makes it a one-sample test. ``None`` when neither
    side has seeds."""
    from agents.stats import paired_seed_test

    if not (a_seeded or b_seeded):
        return None
    seeds = np.asarray([-1 if s is None else s for s, _ in keys])
    groups = [seeds == s for s in np.unique(seeds)]

    def rates(success: np.ndarray, seeded: bool) -> list[float]:
        per = [float(success[g].mean()) for g in groups]
        return per if seeded else per[:1]  # a seedless side repeats the same episodes for every seed

    ra, rb = rates(sa, a_seeded), rates(sb, b_seeded)
    return {**paired_seed_test(ra, rb, confidence), "seeds": [int(s) for s in np.unique(seeds)], "rates_a": ra,
            "rates_b": rb}  # fmt: skip


def _episode_table(
    keys: Sequence[tuple[int | None, int]], sa: np.ndarray, sb: np.ndarray
) -> tuple[int, np.ndarray, np.ndarray]:
    """``(S, a, b)``: the number of seeds among ``keys`` (seed, episode) and both sides' values as ``(E, S)`` arrays over
    the ``E`` episodes every seed ran, in episode and seed order (a side without seeds repeats its value per seed)."""
    per: dict[int, dict[int, tuple[float, float]]] = {}
    for (seed, ep), x, y in zip(keys, sa, sb, strict=True):
        per.setdefault(ep, {})[-1 if seed is None else seed] = (float(x), float(y))
    seeds = sorted({-1 if s is None else s for s, _ in keys})
    full = sorted(ep for ep, by in per.items() if len(by) == len(seeds))
    a = np.asarray([[per[ep][s][0] for s in seeds] for ep in full]).reshape(len(full), len(seeds))
    b = np.asarray([[per[ep][s][1] for s in seeds] for ep in full]).reshape(len(full), len(seeds))
    return len(seeds), a, b


def seeds_against_fixed(
    keys: Sequence[tuple[int | None, int]], sa: np.ndarray, sb: np.ndarray, a_seeded: bool, confidence: float = 0.95
) -> dict[str, Any]:
    """The episode-level success test of a policy with training seeds against one without (a deterministic planner,
    evaluated once on the same episodes), counting each of the planner's episodes once.

    Pooling the ``S`` seeds' (seed, episode) pairs into McNemar's test would count every planner episode ``S`` times
    as if independent. Here each episode ``e`` (of those every seed ran) gives the integer ``d_e = sum_s s_seeded(s, e)
    - S s_fixed(e)`` in ``{-S, ..., S}`` (``s`` = 1 for a success; ``-d_e`` when the seeded side is ``b``);
    ``difference`` = mean ``d`` / ``S`` = the difference of success rates, with a bootstrap percentile interval
    over episodes; the test is the exact sign-flip test of ``d`` (:func:`sign_flip_exact`, H0: ``d`` symmetric
    about 0). Its unit is the episode: the variance between training seeds is the seed-level test's
    (:func:`agents.stats.paired_seed_test`)."""
    n_seeds, a, b = _episode_table(keys, sa, sb)
    full = len(a)
    seeded = a if a_seeded else b
    fixed = (b if a_seeded else a)[:, 0] if full else np.zeros(0)
    d = seeded.sum(axis=1) - n_seeds * fixed
    if not a_seeded:
        d = -d
    test = sign_flip_exact(np.round(d))
    rate_seeded, rate_fixed = float(seeded.mean()) if seeded.size else math.nan, float(fixed.mean()) if full else 0.0
    rate_a, rate_b = (rate_seeded, rate_fixed) if a_seeded else (rate_fixed, rate_seeded)
    return {
        "test": "exact sign-flip over episodes (seeds summed)",
        "n": full,
        "seeds": n_seeds,
        "rate_a": rate_a,
        "rate_b": rate_b,
        "difference": test["mean"] / n_seeds if full else math.nan,
        "difference_ci": list(percentile_mean_ci(d / n_seeds, confidence)),
        "d_counts": test["counts"],
        "statistic": test["statistic"],
        "p_value": test["p_value"],
    }


def seeds_summed(
    keys: Sequence[tuple[int | None, int]], sa: np.ndarray, sb: np.ndarray, confidence: float = 0.95
) -> dict[str, Any]:
    """The episode-level success test of two policies with training seeds (``test_unit: episode``), counting each
    episode once.

    The seeds of both sides replay the same episodes, and which episodes one side wins repeats across seeds, so the
    (seed, episode) pairs of one episode are not independent: McNemar's test over them (``test_unit: pair``) is too
    liberal. Here each episode ``e`` that every seed of the pairs ran gives the integer ``d_e = sum_s (s_a(s, e) -
    s_b(s, e))`` in ``{-S, ..., S}``; ``difference`` = mean ``d`` / ``S`` (the difference of success rates) with a
    bootstrap percentile interval over episodes, and the test is the exact sign-flip test of ``d``
    (:func:`sign_flip_exact`, H0: ``d`` symmetric about 0: swapping the two sides' labels within an episode changes
    nothing), as :func:`seeds_against_fixed` for a seeded policy against a planner. Conditional on the trained
    policies, like McNemar's: the variance between training seeds is the seed-level test's."""
    n_seeds, a, b = _episode_table(keys, sa, sb)
    d = a.sum(axis=1) - b.sum(axis=1)
    test = sign_flip_exact(np.round(d))
    return {
        "test": "exact sign-flip over episodes (seeds summed)",
        "n": len(a),
        "seeds": n_seeds,
        "rate_a": float(a.mean()) if a.size else math.nan,
        "rate_b": float(b.mean()) if b.size else math.nan,
        "difference": test["mean"] / n_seeds if len(a) else math.nan,
        "difference_ci": list(percentile_mean_ci(d / n_seeds, confidence)),
        "d_counts": test["counts"],
        "statistic": test["statistic"],
        "p_value": test["p_value"],
    }


def episode_mean_differences(
    keys: Sequence[tuple[int | None, int]], ta: np.ndarray, tb: np.ndarray, both: np.ndarray
) -> np.ndarray:
    """Per episode, the mean of ``ta - tb`` over the keys (seed, episode) of that episode where ``both`` holds (the
    seeds both sides finished), in episode order; episodes without such a key are left out. Differences are rounded to
    :data:`agents.stats.DIFFERENCE_DECIMALS` before averaging (times on a 0.4 s grid). With one key per episode (two
    policies without seeds) these are the pairs' differences."""
    from agents.stats import DIFFERENCE_DECIMALS

    eps = np.asarray([e for _, e in keys], dtype=np.int64)[both]
    d = np.round(np.asarray(ta, dtype=float)[both] - np.asarray(tb, dtype=float)[both], DIFFERENCE_DECIMALS)
    if eps.size == 0:
        return np.zeros(0)
    order = np.unique(eps)
    where = np.searchsorted(order, eps)
    sums = np.bincount(where, weights=d, minlength=order.size)
    counts = np.bincount(where, minlength=order.size)
    return sums / counts


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
        a_seeded, b_seeded = (any(s is not None for _, s, _ in e.keys) for e in (ea, eb))
        by_episode = cfg.test_unit == "episode"
        if a_seeded != b_seeded:  # a seeded policy against a deterministic one: each of its episodes once
            mc = seeds_against_fixed(keys, sa, sb, a_seeded)
        elif a_seeded and by_episode:  # two seeded policies, the episode the unit: each episode once
            mc = seeds_summed(keys, sa, sb)
        else:
            mc = mcnemar_exact(sa, sb, intervals=intervals)
        seed_level = _seed_level(a_seeded, b_seeded, keys, sa, sb, 0.95)
        tests.append({**base, "endpoint": "success", **mc, **({"seed_level": seed_level} if seed_level else {})})
        both = sa & sb
        if by_episode and (a_seeded or b_seeded):
            means = episode_mean_differences(keys, ta, tb, both)
            wx = wilcoxon_paired(means, np.zeros_like(means))
            population = "episodes with a seed both sides finished (mean difference over those seeds)"
        else:
            wx = wilcoxon_paired(ta[both], tb[both])
            population = "episodes both finished"
        tests.append({**base, "endpoint": "navigation_time_s", "population": population, **wx})
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
        if t["endpoint"] == "success" and not t.get("missing") and "b01" in t:
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


# ----------------------------------------------------------------------------- reacting pedestrians (issue 28)


def percentile_mean_ci(
    values: Sequence[float] | np.ndarray, confidence: float = 0.95, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Bootstrap percentile interval of the mean (``scipy.stats.bootstrap``, ``method="percentile"``; non-finite values
    dropped; none gives ``(nan, nan)``, a constant ``(v, v)``).

    Its bounds are means of resamples of the values, so they stay within the values' range: the interval of a
    non-negative metric (a count, a distance, a delay) is non-negative, and that of a paired difference of {0, 1}
    outcomes within [-2, 2] -- which a normal interval of skewed, zero-heavy data need not be."""
    from scipy import stats

    x = np.asarray(values, dtype=float).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return (math.nan, math.nan)
    if np.all(x == x[0]):
        return (float(x[0]), float(x[0]))
    res = stats.bootstrap(
        (x,), np.mean, n_resamples=n_resamples, confidence_level=confidence, method="percentile",
        vectorized=True, rng=np.random.default_rng(seed),
    )  # fmt: skip
    return (float(res.confidence_interval.low), float(res.confidence_interval.high))


def sign_flip_exact(d: Sequence[int] | np.ndarray) -> dict[str, Any]:
    """Exact two-sided sign-flip test of integer paired values ``d`` (e.g. a difference of paired differences of
    successes, in {-2, ..., 2}): H0 is that ``d`` is symmetric about 0 (``P(d = k) = P(d = -k)``), the McNemar null
    generalised.

    Conditional on the magnitudes, flipping each sign with probability 1/2 makes ``S = sum(d) = sum_k k (2 X_k - n_k)``
    with independent ``X_k ~ Binomial(n_k, 1/2)``, ``n_k`` the number of values of magnitude ``k``: its exact
    distribution is the convolution of the binomial pmfs (``scipy.stats.binom``) placed on multiples of ``k``, and
    ``p = P(|S| >= |s|)`` (``S`` is symmetric). The enumeration ``scipy.stats.permutation_test`` would do is the same
    distribution over ``2**n`` sign vectors, beyond reach for hundreds of non-zero values; with magnitude 1 only this
    is the exact McNemar test (``scipy.stats.binomtest`` on the discordant pairs).

    Returns ``n``, ``n_nonzero``, ``counts`` (values by ``d``), ``statistic`` (``S``), ``mean`` (``S / n``) and
    ``p_value`` (1 without a non-zero value).
    """
    from scipy import stats

    x = np.asarray(d, dtype=float).ravel()
    if x.size and not np.all(x == np.round(x)):
        raise ValueError(f"sign_flip_exact needs integer values, got {x[x != np.round(x)][:3]}")
    v = x.astype(np.int64)
    n = int(v.size)
    s = int(v.sum())
    counts = {str(k): int(c) for k, c in zip(*np.unique(v, return_counts=True), strict=True)}
    out: dict[str, Any] = {"test": "exact sign-flip", "n": n, "n_nonzero": int(np.count_nonzero(v))}
    out.update(counts=counts, statistic=s, mean=s / n if n else math.nan)
    magnitudes = np.abs(v[v != 0])
    if magnitudes.size == 0:
        out["p_value"] = 1.0
        return out
    pmf = np.ones(1)  # of T = sum_k k X_k, on 0 .. sum_k k n_k
    for k, n_k in zip(*np.unique(magnitudes, return_counts=True), strict=True):
        spread = np.zeros(int(k) * int(n_k) + 1)
        spread[:: int(k)] = stats.binom.pmf(np.arange(n_k + 1), n_k, 0.5)
        pmf = np.convolve(pmf, spread)
    total = int(magnitudes.sum())
    values = 2 * np.arange(total + 1) - total  # S = 2 T - total
    # S = 0 is the centre: every outcome is as extreme (summing the pmf would give 1 minus rounding)
    out["p_value"] = 1.0 if s == 0 else float(min(1.0, pmf[np.abs(values) >= abs(s)].sum()))
    return out


def _episode_index(eps: _Episodes) -> dict[tuple[str, int | None, int], int]:
    return {key: i for i, key in enumerate(eps.keys)}


def _success(eps: _Episodes, idx: Sequence[int]) -> np.ndarray:
    return np.asarray(eps.outcome()[list(idx)] == "success", dtype=float)


def _policy_of(cfg: AblationConfig, base: str, reaction: str) -> Any:
    return next((p for p in cfg.policies if p.base == base and cfg.reaction(p) == reaction), None)


def reaction_tests(
    cfg: AblationConfig, pooled: Mapping[tuple[str, str], _Episodes], confidence: float = 0.95
) -> tuple[list[dict[str, Any]], int]:
    """The declared change of each gain across reactions (``reaction_comparisons`` x ``comparisons``).

    For a planner run under reactions ``r`` and ``baseline`` (policies ``<planner>@r`` and ``<planner>@baseline``)
    and a gain ``a - b`` (an arm pair of ``comparisons``), every episode of the fixed lists (each split's, pooled over
    the splits; keyed by split, seed and episode) gives ``d = (s_a,r - s_b,r) - (s_a,baseline - s_b,baseline)`` in
    {-2, ..., 2}, ``s`` its success (1/0) in each of the four cells. ``difference`` = mean ``d`` = the gain under ``r``
    minus the gain under the baseline, with a bootstrap percentile interval over episodes (the four outcomes of an
    episode resampled together); the test is :func:`sign_flip_exact` on ``d``, Holm-adjusted over every test here.
    ``by_split`` gives the same per split, descriptive (its p-values are not in the family).

    Returns the tests (in the order reaction pair, planner, gain) and the family size.
    """
    tests: list[dict[str, Any]] = []
    bases = list(dict.fromkeys(p.base for p in cfg.policies))
    for r, r0 in cfg.reaction_comparisons:
        for base in bases:
            pol, pol0 = _policy_of(cfg, base, r), _policy_of(cfg, base, r0)
            if pol is None or pol0 is None:
                continue
            for a, b in cfg.comparisons:
                if not all(p.uses(cfg.arm(x)) for p in (pol, pol0) for x in (a, b)):
                    continue
                entry: dict[str, Any] = {
                    "comparison": "reactions",
                    "endpoint": "success",
                    "planner": base,
                    "reaction": r,
                    "baseline": r0,
                    "policy": pol.name,
                    "baseline_policy": pol0.name,
                    "gain": {"a": a, "b": b},
                }
                cells = [pooled.get((p.name, x)) for p, x in ((pol, a), (pol, b), (pol0, a), (pol0, b))]
                if any(c is None for c in cells):
                    tests.append({**entry, "missing": True})
                    continue
                indexes = [_episode_index(c) for c in cells if c is not None]
                keys = [k for k in cells[0].keys if all(k in ix for ix in indexes)] if cells[0] else []
                if not keys:
                    tests.append({**entry, "missing": True})
                    continue
                sa, sb, sa0, sb0 = (_success(c, [ix[k] for k in keys]) for c, ix in zip(cells, indexes, strict=True))
                splits = np.asarray([k[0] for k in keys], dtype=object)
                tests.append(
                    {
                        **entry,
                        **_change_of_gain(sa, sb, sa0, sb0, confidence),
                        "by_split": {
                            sp: _change_of_gain(
                                sa[splits == sp], sb[splits == sp], sa0[splits == sp], sb0[splits == sp], confidence
                            )
                            for sp in cfg.splits
                            if np.any(splits == sp)
                        },
                    }
                )
    _holm_family([t for t in tests if not t.get("missing")], cfg.alpha)
    return tests, sum(not t.get("missing") for t in tests)


def _change_of_gain(
    sa: np.ndarray, sb: np.ndarray, sa0: np.ndarray, sb0: np.ndarray, confidence: float
) -> dict[str, Any]:
    """The gain under the reaction and the baseline (means of paired differences, with percentile intervals) and
    the test of their difference (:func:`sign_flip_exact` on ``d``)."""
    d = (sa - sb) - (sa0 - sb0)
    test = sign_flip_exact(d)
    return {
        "test": test["test"],
        "n": test["n"],
        "gain_reaction": float(np.mean(sa - sb)),
        "gain_reaction_ci": list(percentile_mean_ci(sa - sb, confidence)),
        "gain_baseline": float(np.mean(sa0 - sb0)),
        "gain_baseline_ci": list(percentile_mean_ci(sa0 - sb0, confidence)),
        "difference": test["mean"],
        "difference_ci": list(percentile_mean_ci(d, confidence)),
        "d_counts": test["counts"],
        "statistic": test["statistic"],
        "p_value": test["p_value"],
    }


def _holm_family(tests: Sequence[dict[str, Any]], alpha: float) -> None:
    """Holm-adjust the tests' ``p_value`` as one family (``p_holm``, ``family_size``, ``significant``), in place."""
    from agents.stats import holm

    for t, adj in zip(tests, holm([t["p_value"] for t in tests]), strict=True):
        t["p_holm"] = adj
        t["family_size"] = len(tests)
        t["significant"] = bool(adj <= alpha)


def disturbance_summary(eps: _Episodes, confidence: float = 0.95) -> dict[str, Any]:
    """An arm's disturbance metrics (:data:`agents.rollout.DISTURBANCE_METRICS`) over its episodes: for each,
    ``<metric>_mean``, ``<metric>_ci`` (:func:`percentile_mean_ci`, within the metric's range) and ``<metric>_n``;
    and ``disturbed_episodes`` (episodes that disturbed anyone), ``disturbed_episode_rate`` with its Wilson interval.
    Empty when no episode reports them (an archive from before reacting pedestrians: absent, not zero)."""
    from agents.rollout import DISTURBANCE_METRICS
    from agents.stats import wilson_interval

    out: dict[str, Any] = {}
    for metric in DISTURBANCE_METRICS:
        x = eps.metric(metric)
        x = x[np.isfinite(x)]
        if x.size == 0:
            continue
        lo, hi = percentile_mean_ci(x, confidence)
        out.update({f"{metric}_mean": float(x.mean()), f"{metric}_ci": [lo, hi], f"{metric}_n": int(x.size)})
    disturbed = eps.metric("ped_disturbed")
    known = np.isfinite(disturbed)
    if known.any():
        k, n = int(np.sum(disturbed[known] > 0)), int(known.sum())
        out.update(
            disturbed_episodes=k,
            disturbed_episode_rate=k / n,
            disturbed_episode_ci=list(wilson_interval(k, n, confidence)),
        )
    return out


def disturbance_tests(
    cfg: AblationConfig, pooled: Mapping[tuple[str, str], _Episodes], confidence: float = 0.95
) -> tuple[list[dict[str, Any]], dict[str, int]]:
    """The declared disturbance comparisons (``disturbance_comparisons``) within every policy whose pedestrians react
    (a reaction other than ``none``, where every disturbance metric is 0 by definition).

    Pairs: the episodes of the fixed lists both arms finished successfully (so both completed the same trip; a
    collision ends an episode early, a timeout lingers), pooled over the splits. For each metric: the means of both
    arms, the mean difference ``a - b`` with a bootstrap percentile interval over pairs, and the Wilcoxon signed-rank
    test (``agents.stats.wilcoxon_paired``, zero differences dropped), Holm-adjusted within each metric over the
    tests here; ``by_split`` the same estimates per split, descriptive. A pair of cells without the metrics (an
    environment that does not report them) is ``missing``.

    Returns the tests and the family size per metric.
    """
    from agents.rollout import DISTURBANCE_METRICS
    from agents.stats import wilcoxon_paired

    tests: list[dict[str, Any]] = []
    for policy in cfg.policies:
        if cfg.reaction(policy) in (None, "none"):
            continue
        for a, b in cfg.disturbance_comparisons:
            if not (policy.uses(cfg.arm(a)) and policy.uses(cfg.arm(b))):
                continue
            base = {"comparison": "disturbance", "policy": policy.name, "reaction": cfg.reaction(policy)}
            base.update(a=a, b=b, population="episodes both arms finished successfully")
            ea, eb = pooled.get((policy.name, a)), pooled.get((policy.name, b))
            if ea is None or eb is None:
                tests += [{**base, "endpoint": m, "missing": True} for m in DISTURBANCE_METRICS]
                continue
            ib = _episode_index(eb)
            keys = [k for k in ea.keys if k in ib]
            ia = _episode_index(ea)
            both = [k for k in keys if ea.rows[ia[k]].get("outcome") == "success" == eb.rows[ib[k]].get("outcome")]
            splits = np.asarray([k[0] for k in both], dtype=object)
            for metric in DISTURBANCE_METRICS:
                x = ea.metric(metric)[[ia[k] for k in both]] if both else np.zeros(0)
                y = eb.metric(metric)[[ib[k] for k in both]] if both else np.zeros(0)
                if not (np.isfinite(ea.metric(metric)).any() and np.isfinite(eb.metric(metric)).any()):
                    tests.append({**base, "endpoint": metric, "missing": True})
                    continue
                entry = {**base, "endpoint": metric, **_paired_metric(x, y, confidence)}
                entry.update(wilcoxon_paired(x, y))
                entry["by_split"] = {
                    sp: _paired_metric(x[splits == sp], y[splits == sp], confidence)
                    for sp in cfg.splits
                    if np.any(splits == sp)
                }
                tests.append(entry)
    families: dict[str, int] = {}
    for metric in DISTURBANCE_METRICS:
        members = [t for t in tests if t["endpoint"] == metric and not t.get("missing")]
        _holm_family(members, cfg.alpha)
        families[metric] = len(members)
    return tests, families


def _paired_metric(x: np.ndarray, y: np.ndarray, confidence: float) -> dict[str, Any]:
    """Means of paired values (pairs with a non-finite member dropped) and of their difference, with a percentile
    interval."""
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    n = int(x.size)
    return {
        "pairs": n,
        "mean_a": float(x.mean()) if n else math.nan,
        "mean_b": float(y.mean()) if n else math.nan,
        "difference": float((x - y).mean()) if n else math.nan,
        "difference_ci": list(percentile_mean_ci(x - y, confidence)),
    }
