"""The claims test (density, motion type, collisions, difficulty) on tiny constructed windows whose
answers are known, its block-bootstrap intervals against a naive loop, and the merge into the page."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS
from crowdnav_mesrnn.evaluation.statistics import combine_interval, ratio_differences
from crowdnav_mesrnn.studies.claims import compute
from crowdnav_mesrnn.studies.claims.measure import MOTIONS, colliding_pairs, density_bin, measure_batch, motion_types

K = np.arange(1, PRED_LEN + 1, dtype=float)


def test_density_bins_are_the_declared_ones() -> None:
    others = np.array([0, 1, 2, 3, 5, 6, 10, 11, 40])
    np.testing.assert_array_equal(density_bin(others), [-1, 0, 0, 1, 1, 2, 2, 3, 3])


def test_motion_types_of_known_futures() -> None:
    """Standing still with jitter, walking straight, a right-angle turn, a stop, and the same 1.2 m
    displacement at the two annotation steps (0.25 m/s in 4.8 s: linear; 0.15 m/s in eth's 8 s: near-stationary)."""
    p0 = np.zeros((1, 7, 2))
    fut = np.zeros((1, PRED_LEN, 7, 2))
    fut[0, :, 0] = 0.02 * np.stack([np.sin(K), np.cos(K)], -1)  # jitter around the start
    fut[0, :, 1, 0] = 0.48 * K  # 1.2 m/s straight
    fut[0, :6, 2, 0] = 0.48 * K[:6]  # right-angle turn after 6 steps
    fut[0, 6:, 2, 0] = 0.48 * 6
    fut[0, 6:, 2, 1] = 0.48 * K[:6]
    fut[0, :, 3, 0] = np.minimum(0.48 * K, 1.44)  # walks 3 steps, then stops
    fut[0, :, 4, 0] = 0.1 * K  # 1.2 m in 12 steps
    fut[0, :, 5] = fut[0, :, 4]
    fut[0, :, 6, 0] = 0.48 * K + 0.1 * np.sin(K)  # straight with small wobble
    kinds = motion_types(p0, fut, np.array([0.4]))[0]
    assert [MOTIONS[k] for k in kinds[[0, 1, 2, 3, 4, 6]]] == [
        "near-stationary",
        "linear",
        "non-linear",
        "non-linear",
        "linear",
        "linear",
    ]
    eth = motion_types(p0, fut, np.array([10 / 15]))[0]
    assert MOTIONS[eth[5]] == "near-stationary" and MOTIONS[eth[1]] == "linear"


def test_colliding_pairs_count_scored_pairs_closer_than_the_distance_at_any_step() -> None:
    traj = np.zeros((1, PRED_LEN, 4, 2))
    traj[0, :, 0, 0] = K  # walks +x along y = 0
    traj[0, :, 1, 0] = 12 - K  # walks -x along y = 0.15: they pass within 0.15 m
    traj[0, :, 1, 1] = 0.15
    traj[0, :, 2] = [50.0, 50.0]  # far away
    traj[0, :, 3] = traj[0, :, 0]  # on top of pedestrian 0, but not scored
    coll, pairs = colliding_pairs(traj, np.array([[True, True, True, False]]), 0.2)
    assert coll.tolist() == [1] and pairs.tolist() == [3]
    coll, _ = colliding_pairs(traj, np.array([[True, True, True, False]]), 0.1)
    assert coll.tolist() == [0]


def test_measure_batch_of_a_constructed_window() -> None:
    """Two scored pedestrians walking straight 1 m apart, one context pedestrian present at the last
    observed step only, one absent there: density 2 others; a forecast 0.5 m off for the first scored."""
    t = OBS_LEN + PRED_LEN
    pos = np.zeros((1, t, 4, 2))
    pres = np.zeros((1, t, 4), bool)
    steps = np.arange(t, dtype=float)
    pos[0, :, 0, 0] = 0.48 * steps
    pos[0, :, 1, 0] = 0.48 * steps
    pos[0, :, 1, 1] = 1.0
    pres[0, :, :2] = True
    pres[0, OBS_LEN - 1, 2] = True
    pres[0, 0, 3] = True
    scored = np.array([[True, True, False, False]])
    pred = pos[:, OBS_LEN:].copy()
    pred[0, :, 0, 1] += 0.5
    m = measure_batch(pos, pres, scored, pred, np.array([0.4]))
    assert m["others"].tolist() == [2] and m["pedestrians"].tolist() == [2]
    assert m["ade_m"] == pytest.approx([0.5]) and m["fde_m"] == pytest.approx([0.5])
    assert m["ade_matched_m"] == pytest.approx([0.5])
    assert m["motion_count"][:, 0].tolist() == [0, 2, 0]  # both linear
    assert m["motion_ade_m"][:, 0] == pytest.approx([0.0, 0.5, 0.0])
    assert m["pairs"].tolist() == [1] and m["collisions"].tolist() == [0] and m["gt_collisions"].tolist() == [0]
    pred[0, :, 0, 1] += 0.4  # now 0.1 m from the other forecast
    assert measure_batch(pos, pres, scored, pred, np.array([0.4]))["collisions"].tolist() == [1]
    # eth's step: the matched horizon keeps the first 7 steps (4.67 s); errors growing by 0.1 m a step
    pred = pos[:, OBS_LEN:].copy()
    pred[0, :, :2, 1] += 0.1 * K[:, None]
    m = measure_batch(pos, pres, scored, pred, np.array([10 / 15]))
    assert m["ade_matched_m"] == pytest.approx([2 * 0.4]) and m["ade_m"] == pytest.approx([2 * 0.65])


def naive_ratio_interval(a, b, den, contrast, block_len, n, seed):
    """The same statistic by explicit loops: each replicate concatenates blocks window by window."""
    rngs = np.random.default_rng(seed).spawn(len(den))
    draws = []
    for d, rng in zip(den, rngs, strict=True):
        w = d.shape[1]
        length = min(block_len, w)
        draws.append(rng.integers(0, w - length + 1, size=(n, math.ceil(w / length))))
    c = den[0].shape[0]
    reps = np.zeros((c + 1, n))
    for r in range(n):
        num_tot, den_tot = np.zeros(c), np.zeros(c)
        for x, y, d, starts in zip(a, b, den, draws, strict=True):
            w = d.shape[1]
            length = min(block_len, w)
            idx = [i for st in starts[r] for i in range(st, st + length)][:w]
            for i in idx:
                num_tot += x.mean(0)[:, i] - y.mean(0)[:, i]
                den_tot += d[:, i]
        ratio = num_tot / den_tot
        reps[:c, r] = ratio
        reps[c, r] = ratio[contrast[0]] - ratio[contrast[1]]
    return reps


def tiny_case(seeds_a: int = 1):
    rng = np.random.default_rng(7)
    den = [rng.integers(1, 4, size=(2, w)).astype(float) for w in (7, 5)]
    a = [rng.normal(0.5, 0.2, size=(seeds_a, 2, d.shape[1])) * d for d in den]
    b = [rng.normal(0.6, 0.2, size=(1, 2, d.shape[1])) * d for d in den]
    return a, b, den


def test_ratio_difference_intervals_equal_a_naive_loop() -> None:
    a, b, den = tiny_case()
    res = ratio_differences(a, b, den, [(1, 0)], block_len=3, n_resamples=300, seed=4)
    reps = naive_ratio_interval(a, b, den, (1, 0), 3, 300, 4)
    for i, (d, empty) in enumerate(res):
        assert empty == 0.0
        np.testing.assert_allclose(d.interval, np.quantile(reps[i], [0.025, 0.975]), rtol=0, atol=1e-12)
    est = (sum((x - y)[0].sum(1) for x, y in zip(a, b, strict=True))) / sum(d.sum(1) for d in den)
    assert res[0][0].estimate == pytest.approx(est[0]) and res[2][0].estimate == pytest.approx(est[1] - est[0])
    # one split alone: its own windows only
    single = ratio_differences(a[:1], b[:1], den[:1], block_len=3, n_resamples=300, seed=4)
    reps1 = naive_ratio_interval(a[:1], b[:1], den[:1], (1, 0), 3, 300, 4)
    np.testing.assert_allclose(single[1][0].interval, np.quantile(reps1[1], [0.025, 0.975]), atol=1e-12)


def test_ratio_difference_over_seeds_adds_the_seed_variance() -> None:
    a, b, den = tiny_case(seeds_a=3)
    d, _ = ratio_differences(a, b, den, block_len=3, n_resamples=300, seed=4)[1]
    reps = naive_ratio_interval(a, b, den, (1, 0), 3, 300, 4)
    per_seed = sum(x[:, 1].sum(1) for x in a) / sum(x[1].sum() for x in den)
    ref = combine_interval(d.estimate, reps[1], [per_seed, np.zeros(1)])
    np.testing.assert_allclose(d.interval, ref.interval, atol=1e-12)
    assert d.seed_se == pytest.approx(per_seed.std(ddof=1) / np.sqrt(3)) and d.df > 2.0  # windows add df


def test_an_empty_category_has_no_estimate_and_a_rare_one_reports_its_empty_resamples() -> None:
    den = [np.array([[1.0, 1, 1, 1, 1, 1, 1, 1], [0, 0, 0, 0, 0, 0, 0, 3]])]
    a = [np.ones((1, 2, 8)) * den[0]]
    res = ratio_differences(a, None, den, block_len=2, n_resamples=500, seed=0)
    assert res[0][0].estimate == pytest.approx(1.0) and res[0][1] == 0.0
    assert res[1][0].estimate == pytest.approx(1.0) and 0.3 < res[1][1] < 0.9  # the last window is rarely drawn
    den[0][1] = 0
    assert math.isnan(ratio_differences(a, None, den, n_resamples=50)[1][0].estimate)


# ------------------------------------------------------------------ the whole claims object
def fake_measured(windows: int = 80, seeds: int = 1) -> compute.Measured:
    """Windows alternating sparse (2 others) and dense (12 others) in runs of 10; everything scored is
    near-stationary or linear by construction. MESRNN errs 0.3 m less than the others in dense windows
    and the same in sparse ones (the same window noise for every model; seed k adds 0.01 k m); its
    forecasts never collide, the others' collide in every dense window; ETH's scenes are the harder."""
    rng = np.random.default_rng(0)
    out: compute.Measured = {m: {} for m in compute.MODELS}
    for split in SPLITS:
        dense = (np.arange(windows) // 10) % 2 == 1
        peds = np.full(windows, 4.0)
        others = np.where(dense, 12.0, 2.0)
        motion = np.stack([np.full(windows, 1.0), np.full(windows, 3.0), np.zeros(windows)])
        truth = {
            "pedestrians": peds,
            "others": others,
            "motion_count": motion,
            "pairs": np.full(windows, 6.0),
            "gt_collisions": np.zeros(windows),
        }
        noise = 0.05 * rng.normal(size=windows) + (0.2 if split in ("eth", "hotel") else 0.0)  # ETH the harder
        for m in compute.MODELS:
            runs = []
            for k in range(seeds if m != "cv" else 1):
                per = 1.0 + noise + 0.01 * k - (0.3 if m == "mesrnn" else 0.0) * dense
                runs.append(
                    truth
                    | {
                        "ade_m": per * peds,
                        "fde_m": 2 * per * peds,
                        "ade_matched_m": per * peds,
                        "motion_ade_m": motion * per,
                        "motion_fde_m": 2 * motion * per,
                        "collisions": np.where(dense & (m != "mesrnn"), 1.0, 0.0),
                    }
                )
            out[m][split] = runs
    return out


def test_claims_results_read_the_constructed_answers() -> None:
    c = compute.claims_results(fake_measured(), "synthetic", n_resamples=300)
    for family in ("density", "motion", "collisions"):
        assert set(c[family]["models"]) == set(compute.MODELS)
        assert set(c[family]["differences"]) == {"mesrnn-srnn", "mesrnn-vlstm", "mesrnn-cv"}
    den = c["density"]
    assert den["labels"] == ["1–2", "3–5", "6–10", "11+"]
    assert den["weights"]["pooled"] == {"1–2": 4 * 40 * 5, "3–5": 0, "6–10": 0, "11+": 4 * 40 * 5}
    assert den["models"]["srnn"]["ade_m"]["pooled"]["3–5"] is None  # empty: not reported
    cell = den["differences"]["mesrnn-srnn"]["ade_m"]["pooled"]
    assert cell["11+"]["diff"] == pytest.approx(-0.3, abs=0.02) and cell["11+"]["reading"] == "negative"
    assert cell["1–2"]["reading"] == "no detectable difference"
    assert cell["contrast"]["bins"] == ["1–2", "11+"] and cell["contrast"]["reading"] == "negative"
    assert den["pooled_split_shares"]["11+"]["dominated_by"] is None  # five equal splits
    coll = c["collisions"]
    assert coll["ground_truth"]["pooled"]["dense"] == 0.0
    assert coll["models"]["srnn"]["pooled"]["dense"] == pytest.approx(1 / 6)
    assert coll["differences"]["mesrnn-cv"]["pooled"]["dense"]["diff"] == pytest.approx(-1 / 6)
    assert coll["against_ground_truth"]["mesrnn"]["pooled"]["all"]["diff"] == 0.0
    assert c["motion"]["weights"]["pooled"] == {"near-stationary": 400, "linear": 1200, "non-linear": 0}
    v = c["verdicts"]
    assert v["density"]["overall"] == "holds" and v["collisions"]["overall"] == "holds"
    assert v["motion"]["per_baseline"]["mesrnn-cv"] == "holds"  # stationary pedestrians are in dense windows too
    assert v["difficulty"]["parts"]["ucy_denser"] is False  # every split equally dense
    assert v["difficulty"]["overall"] == "contradicted"
    json.dumps(c)  # JSON-ready


def test_claims_over_seeds_and_the_page_section() -> None:
    from crowdnav_mesrnn.studies.claims.render import render_claims

    c = compute.claims_results(fake_measured(seeds=3), "seeds [0, 1, 2] of plan `p.yaml`", n_resamples=200)
    assert c["seeds"] == {"cv": 1, "vlstm": 3, "srnn": 3, "mesrnn": 3}
    e = c["density"]["differences"]["mesrnn-srnn"]["ade_m"]["pooled"]["11+"]
    assert e["diff"] == pytest.approx(-0.3) and e["window_se"] == pytest.approx(0.0, abs=1e-12)
    assert e["seed_se"] == pytest.approx(0.01 * math.sqrt(2 / 3))  # seeds 0, 0.01, 0.02 on each side
    e = c["density"]["differences"]["mesrnn-cv"]["ade_m"]["pooled"]["11+"]
    assert e["diff"] == pytest.approx(-0.29) and e["seed_se"] == pytest.approx(0.01 / math.sqrt(3))
    assert e["df"] == pytest.approx(2.0) and e["ci"][1] - e["ci"][0] == pytest.approx(
        2 * 4.303 * 0.01 / math.sqrt(3), rel=1e-3
    )
    page = "\n".join(render_claims(c))
    for needle in (
        "Weights: seeds [0, 1, 2] of plan `p.yaml`.",
        "**(a) MESRNN adapts to density — holds.**",
        "**(b) Near-stationary pedestrians predicted much better — holds.**",
        "**(c) The UCY scenes are harder because denser — contradicted.**",
        "eth's annotation step is 0.667 s",
        "| MESRNN − SRNN | pooled |",
        compute.COMMAND,
    ):
        assert needle in page, needle
    assert "Not computed" in "\n".join(render_claims(None))


def test_a_bin_dominated_by_one_scene_is_named() -> None:
    m = fake_measured()
    for model in compute.MODELS:
        for split in SPLITS[1:]:
            for run in m[model][split]:
                run["others"] = np.full_like(run["others"], 2.0)  # only eth has dense windows
    c = compute.claims_results(m, "synthetic", n_resamples=100)
    assert c["density"]["pooled_split_shares"]["11+"]["dominated_by"] == "eth"
    from crowdnav_mesrnn.studies.claims.render import render_claims

    assert "11+: eth 100 %" in "\n".join(render_claims(c))


def test_headline_check_catches_other_weights() -> None:
    m = fake_measured()
    headline = {
        model: {
            "splits": {
                s: {"ade_m": float(r[0]["ade_m"].sum() / r[0]["pedestrians"].sum())} for s, r in m[model].items()
            }
        }
        for model in compute.MODELS
    }
    compute.check_headline(m, headline)
    headline["srnn"]["splits"]["zara1"]["ade_m"] += 0.01
    with pytest.raises(ValueError, match="srnn on zara1"):
        compute.check_headline(m, headline)


# ------------------------------------------------------------------ merging into the page
def saved_results() -> dict:
    """A saved main page's JSON (synthetic): four models, their comparisons, a plan's seeds section."""
    from crowdnav_mesrnn.studies.report import compare

    m = fake_measured(windows=40)
    errors = {
        model: {
            s: {"ade_m": r[0]["ade_m"], "fde_m": r[0]["fde_m"], "pedestrians": r[0]["pedestrians"].astype(int)}
            for s, r in runs.items()
        }
        for model, runs in m.items()
    }
    results = {}
    for model, errs in errors.items():
        splits = {
            s: {k: float(e[k].sum() / e["pedestrians"].sum()) for k in ("ade_m", "fde_m")} for s, e in errs.items()
        }
        splits = {s: v | {"ade_norm": v["ade_m"] / 10, "fde_norm": v["fde_m"] / 10} for s, v in splits.items()}
        splits["average"] = {k: float(np.mean([splits[s][k] for s in SPLITS])) for k in splits["eth"]}
        results[model] = {"model": model, "part": "test", "splits": splits}
        if model != "cv":
            results[model]["checkpoints"] = {s: {"note": "plan configs/predictor/candidates.yaml"} for s in SPLITS}
    results["comparisons"] = compare(errors, n_resamples=50)
    results["bootstrap"] = {"block_len_windows": 20, "resamples": 50}
    results["seeds"] = {
        "plan": "configs/predictor/candidates.yaml",
        "seeds": [0, 1, 2],
        "rows": {},
        "average": {},
        "comparisons": {},
    }
    return results


def test_add_claims_keeps_every_key(tmp_path, monkeypatch) -> None:
    """``report --claims`` adds the claims object and keeps every other key of the saved JSON exactly;
    the page is re-rendered from the merged JSON."""
    from crowdnav_mesrnn.cli import main
    from crowdnav_mesrnn.studies.report import add_claims
    from crowdnav_mesrnn.studies.report_render import render

    saved = saved_results()
    saved["an_unknown_section"] = {"kept": [1, 2, 3]}
    claims = compute.claims_results(fake_measured(), "synthetic", n_resamples=100)
    merged = add_claims(saved, claims)
    assert all(merged[k] == v for k, v in saved.items()) and set(merged) == {*saved, "claims"}
    again = add_claims(merged, claims | {"weights": "other"})
    assert set(again) == set(merged) and again["claims"]["weights"] == "other"
    with pytest.raises(ValueError, match="main page"):
        add_claims({**saved, "plan_only": True}, claims)

    del saved["an_unknown_section"]  # (the page renders unknown keys as rows of the headline table)
    out = tmp_path / "page.md"
    assert main(["predictor", "report", "--claims", "--out", str(out)]) == 2  # no JSON to add to
    out.with_suffix(".json").write_text(json.dumps(saved))
    seen = {}

    def fake_compute(data_dir, plan, block_len, n_resamples, headline=None):
        seen["plan"] = plan
        return claims

    monkeypatch.setattr(compute, "compute_claims", fake_compute)
    assert main(["predictor", "report", "--claims", "--out", str(out)]) == 0
    written = json.loads(out.with_suffix(".json").read_text())
    assert {k: written[k] for k in saved} == json.loads(json.dumps(saved)) and "claims" in written
    assert seen["plan"] == "configs/predictor/candidates.yaml"  # the plan the page was made with
    page = out.read_text()
    assert page == render(written) and "### Verdicts" in page and "## Paired differences" in page


def test_the_whole_report_includes_the_claims(monkeypatch) -> None:
    """``build_report`` (``predictor report [--plan]``) computes the claims with the same plan and puts
    them on the page (evaluation and measurement replaced by synthetic ones)."""
    from crowdnav_mesrnn.studies import report

    saved = saved_results()
    m = fake_measured(windows=40)

    def fake_eval(model, splits="all", data_dir=None, window_sums=None, **_):
        for s, runs in m[model].items():
            window_sums[s] = {
                "ade_m": runs[0]["ade_m"],
                "fde_m": runs[0]["fde_m"],
                "pedestrians": runs[0]["pedestrians"],
            }
        return saved[model]

    seen = {}

    def fake_compute(data_dir, plan, block_len, n_resamples, headline=None):
        seen["plan"], seen["headline"] = plan, headline
        return compute.claims_results(m, "synthetic", n_resamples=50) | {"headline_checked": True}

    monkeypatch.setattr(report, "evaluate_model", fake_eval)
    monkeypatch.setattr(compute, "compute_claims", fake_compute)
    page, results = report.build_report(n_resamples=50)
    assert seen["plan"] is None and seen["headline"] is results and "claims" in results
    assert "**(b) Near-stationary pedestrians predicted much better" in page
    assert "equals the headline table's (same windows, same weights" in page
    assert "do not include seed-to-seed variation" in page
    page, results = report.build_report(n_resamples=50, claims=False)
    assert "claims" not in results and "Not computed: run `crowdnav-mesrnn predictor report --claims" in page


def test_weights_are_the_plan_seeds_only_when_its_folders_hold_them_all(tmp_path) -> None:
    """Shipped weights without a plan, or while any (model, split) lacks a seed; the plan's seed
    checkpoints (in seed order) once every seed of every (model, split) is done."""
    from crowdnav_mesrnn.studies.plan import REPO_ROOT, load_plan, run_dir

    text = (REPO_ROOT / "configs/predictor/candidates.yaml").read_text()
    (tmp_path / "plan.yaml").write_text(text.replace("out_dir: runs/predictor/plan", f"out_dir: {tmp_path}"))
    plan = load_plan(tmp_path / "plan.yaml")

    def done(model: str, split: str, cand: str, seed: int, val: float) -> None:
        out = run_dir(plan, model, split, cand, seed)
        out.mkdir(parents=True, exist_ok=True)
        (out / "done.json").write_text(json.dumps({"best_val_ade_m": val, "epochs": 1}))

    assert compute.weights_for(None)[0] is None and "without a plan" in compute.weights_for(None)[1]
    for m in plan.models:
        for s in plan.splits:
            for i, c in enumerate(plan.candidates):
                done(m, s, c.name, plan.selection_seed, 0.5 + 0.1 * i)  # the first candidate is selected
            for k in plan.seeds[:-1]:
                done(m, s, plan.candidates[0].name, k, 0.5)
    seeds, why = compute.weights_for(tmp_path / "plan.yaml")
    assert seeds is None and "do not hold every seed of 15 of 15" in why
    for m in plan.models:
        for s in plan.splits:
            done(m, s, plan.candidates[0].name, plan.seeds[-1], 0.5)
    seeds, why = compute.weights_for(tmp_path / "plan.yaml")
    assert why.startswith(f"seeds {list(plan.seeds)} of plan") and set(seeds) == {"vlstm", "srnn", "mesrnn"}
    assert seeds["mesrnn"]["zara2"] == [
        str(run_dir(plan, "mesrnn", "zara2", plan.candidates[0].name, k) / "best.pt") for k in plan.seeds
    ]
