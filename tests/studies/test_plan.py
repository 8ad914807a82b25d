"""The comparison plan: every candidate applied to every model, expansion, selection on validation,
resumable execution and export of the best-validation seed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import crowdnav_mesrnn.models.pretrained as pretrained
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.studies.plan import (
    REPO_ROOT,
    candidate_runs,
    execute,
    load_plan,
    parse_shard,
    run_dir,
    run_lock,
    selected_candidate,
    shard_filter,
    stage_runs,
    status,
    summary,
)
from crowdnav_mesrnn.training.trainer import load_configs

SHIPPED = REPO_ROOT / "configs" / "predictor" / "candidates.yaml"


def test_every_candidate_is_applied_to_every_model() -> None:
    plan = load_plan(SHIPPED)
    assert (
        set(plan.models) == set(predictors.names(predictors.PRETRAINED, plugins=False))
        and len(plan.splits) == 5
        and len(plan.seeds) >= 3
    )
    runs = candidate_runs(plan)
    assert len(runs) == len(plan.models) * len(plan.splits) * len(plan.candidates)
    combos = {(r.model, r.split, r.candidate.name) for r in runs}
    assert combos == {(m, s, c.name) for m in plan.models for s in plan.splits for c in plan.candidates}
    assert len({r.out for r in runs}) == len(runs)
    for cand in plan.candidates:
        resolved = {}
        for model in plan.models:
            mcfg, tcfg = load_configs(model, cand.config_path(model), {**cand.overrides, "split": "eth", "seed": 0})
            assert mcfg.model == model and tcfg.seed == 0 and tcfg.split == "eth"
            resolved[model] = (tcfg, {k: v for k, v in mcfg.to_dict().items() if k not in ("model", "types")})
        # The same training recipe and the same architecture options for every model.
        assert len({repr(t) for t, _ in resolved.values()}) == 1, cand.name
        assert len({json.dumps(a, sort_keys=True) for _, a in resolved.values()}) == 1, cand.name
    rotation = next(c for c in plan.candidates if c.name == "residual_rotation")
    for model in plan.models:
        assert load_configs(model, rotation.config_path(model), rotation.overrides)[1].augment_rotation
    run = runs[0]
    assert f"--model {run.model} --split {run.split}" in run.command() and "--set seed=0" in run.command()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("models: [lstm]\ncandidates: {a: {config: 'configs/predictor/{model}.yaml'}}\n", "unknown model 'lstm'"),
        ("candidates: {a: {config: 'configs/predictor/{model}.yaml', set: {seed: 3}}}\n", "may not set 'seed'"),
        ("candidates: {a: {config: 'nowhere/{model}.yaml'}}\n", "no config"),
        ("seeds: [1, 2]\ncandidates: {a: {config: 'configs/predictor/{model}.yaml'}}\n", "selection_seed 0 must be"),
        ("candidates: {a: {config: 'configs/predictor/{model}.yaml'}}\nepochs: 3\n", "valid keys"),
        ("candidates: {a: {config: 'configs/predictor/{model}.yaml'}}\nexport: 'no'\n", "'export' is 'no'"),
    ],
)
def test_plan_errors(tmp_path: Path, text: str, message: str) -> None:
    bad = tmp_path / "p.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_plan(bad)


def test_shard_syntax() -> None:
    assert parse_shard("1/2") == (1, 2)
    with pytest.raises(ValueError, match="i/n"):
        parse_shard("2")


def _fake_done(out: Path, val: float, epochs: int = 1) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "done.json").write_text(json.dumps({"best_val_ade_m": val, "epochs": epochs}))


def test_selection_on_validation_then_seed_expansion_and_shards(tmp_path: Path) -> None:
    text = SHIPPED.read_text().replace("out_dir: runs/predictor/plan", f"out_dir: {tmp_path}")
    (tmp_path / "plan.yaml").write_text(text)
    plan = load_plan(tmp_path / "plan.yaml")
    runs, waiting = stage_runs(plan, "seeds")
    assert runs == [] and len(waiting) == len(plan.models) * len(plan.splits)
    vals = {"paper": 0.9, "residual": 0.45, "residual_rotation": 0.44}
    for name, val in list(vals.items())[:2]:
        _fake_done(run_dir(plan, "srnn", "hotel", name, plan.selection_seed), val)
    assert selected_candidate(plan, "srnn", "hotel")[0] is None  # one candidate still missing
    _fake_done(run_dir(plan, "srnn", "hotel", "residual_rotation", plan.selection_seed), vals["residual_rotation"])
    cand, got = selected_candidate(plan, "srnn", "hotel")
    assert cand is not None and cand.name == "residual_rotation" and got == vals
    runs, waiting = stage_runs(plan, "seeds")
    assert [(r.model, r.split, r.candidate.name, r.seed) for r in runs] == [
        ("srnn", "hotel", "residual_rotation", k) for k in plan.seeds if k != plan.selection_seed
    ]
    assert ("srnn", "hotel") not in waiting
    assert status(runs[0]) == ("todo", 0)
    for k, val in zip([k for k in plan.seeds if k != plan.selection_seed], [0.43, 0.47], strict=False):
        _fake_done(run_dir(plan, "srnn", "hotel", "residual_rotation", k), val)
    row = summary(plan)["srnn/hotel"]
    assert row["selected"] == "residual_rotation" and row["shipped_seed"] == 1
    every = candidate_runs(plan)
    shards = [shard_filter(every, (i, 3), plan) for i in range(3)]
    assert sorted(r.out for s in shards for r in s) == sorted(r.out for r in every)
    assert not set(r.out for r in shards[0]) & set(r.out for r in shards[1])


def test_seed_shards_stay_put_while_selection_grows(tmp_path: Path) -> None:
    text = SHIPPED.read_text().replace("out_dir: runs/predictor/plan", f"out_dir: {tmp_path}")
    (tmp_path / "plan.yaml").write_text(text)
    plan = load_plan(tmp_path / "plan.yaml")

    def select(model: str, split: str) -> None:
        for c in plan.candidates:
            _fake_done(run_dir(plan, model, split, c.name, plan.selection_seed), 0.5)

    def owners() -> dict[Path, int]:
        runs, _ = stage_runs(plan, "seeds")
        return {r.out: i for i in range(2) for r in shard_filter(runs, (i, 2), plan)}

    select("srnn", "univ")
    before = owners()
    select("vlstm", "eth")  # a pair earlier in the grid becomes selected after srnn/univ
    after = owners()
    assert len(after) == 2 * len(before)
    assert all(after[out] == shard for out, shard in before.items())  # nobody changed shard
    assert sorted(after.values()) == [0, 0, 1, 1]  # and the work is split evenly


def test_a_run_trained_elsewhere_is_skipped(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with run_lock(out) as first:
        assert first
        with run_lock(out) as second:  # another open file description: as another process would be
            assert not second
    with run_lock(out) as again:  # released when the holder is done
        assert again


def test_execute_is_resumable_and_exports_the_best_seed(
    tmp_path: Path, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    tiny = "{node_embed: 8, node_hidden: 16, edge_embed: 4, edge_hidden: 8, max_windows: 16, epochs: 1, batch_size: 8}"
    (tmp_path / "plan.yaml").write_text(
        f"models: [vlstm]\nsplits: [zara1]\nseeds: [0, 1]\nout_dir: {tmp_path / 'runs'}\ncandidates:\n"
        f"  a: {{config: 'configs/predictor/{{model}}_residual.yaml', set: {tiny}}}\n"
        f"  b: {{config: 'configs/predictor/{{model}}.yaml', set: {tiny}}}\n"
    )
    plan = load_plan(tmp_path / "plan.yaml")
    lines: list[str] = []
    assert execute(plan, "all", data_dir=str(data_dir), log=lines.append) == 0
    assert sum("done: best val ADE" in line for line in lines) == 3  # two candidates, one more seed
    lines.clear()
    assert execute(plan, "all", data_dir=str(data_dir), log=lines.append) == 0
    assert not any("done: best val ADE" in line for line in lines)  # nothing retrained
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "shipped")
    assert execute(plan, "export", log=lines.append) == 0
    row = summary(plan)["vlstm/zara1"]
    shipped = pretrained.load_predictor(tmp_path / "shipped" / "vlstm_zara1.pt", "vlstm", "zara1")
    note = shipped.info["selection"]["note"]
    assert note.startswith("lowest val ADE") and f"seed {row['shipped_seed']})" in note
    assert f"candidate {row['selected']} selected on val ADE" in note

    # The report's seed section, end to end on these runs: every seed and candidate on test, and the
    # comparison over seeds against constant velocity.
    from crowdnav_mesrnn.evaluation.protocol import evaluate_model
    from crowdnav_mesrnn.studies.report import seed_results
    from crowdnav_mesrnn.studies.report_render import render_seeds

    cv: dict = {}
    evaluate_model("cv", ["zara1"], data_dir=str(data_dir), window_sums=cv)
    res = seed_results(tmp_path / "plan.yaml", str(data_dir), cv, n_resamples=200)
    got = res["rows"]["vlstm/zara1"]
    assert set(got["seeds"]) == {0, 1} and got["test"]["n"] == 2 and set(got["candidates_test"]) == {"a", "b"}
    assert got["candidates_test"][got["selected"]] == got["seeds"][0]["test"]
    diff = res["comparisons"]["vlstm-cv"]["ade_m"]["zara1"]
    assert diff["seeds"] == [2, 1] and diff["ci"][0] <= diff["diff"] <= diff["ci"][1]
    assert (
        abs(
            diff["diff"]
            - (got["test"]["ade_m"]["mean"] - cv["zara1"]["ade_m"].sum() / cv["zara1"]["pedestrians"].sum())
        )
        < 1e-9
    )
    assert "| VLSTM | a |" in "\n".join(render_seeds(res))


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
def test_dry_run_lists_every_run_with_a_cpu_estimate(tmp_path: Path, data_dir: Path) -> None:
    from crowdnav_mesrnn.studies.plan_budget import dry_run

    tiny = "{node_embed: 8, node_hidden: 16, edge_embed: 4, edge_hidden: 8, epochs: 2}"
    (tmp_path / "plan.yaml").write_text(
        f"models: [vlstm, srnn]\nsplits: [zara1, hotel]\nseeds: [0, 1, 2]\nout_dir: {tmp_path / 'runs'}\n"
        f"candidates:\n  a: {{config: 'configs/predictor/{{model}}_residual.yaml', set: {tiny}}}\n"
        f"  b: {{config: 'configs/predictor/{{model}}.yaml', set: {tiny}}}\n"
    )
    plan = load_plan(tmp_path / "plan.yaml")
    text = dry_run(plan, "all", measure_batches=1, data_dir=str(data_dir))
    assert (tmp_path / "runs" / "rates.json").is_file()
    rows = [line for line in text.splitlines() if line.startswith(("candidates ", "seeds "))]
    assert len(rows) == 2 * 2 * 2 + 2 * 2 * 2  # candidates, then two more seeds per (model, split)
    assert sum("waits" in r for r in rows) == 8 and all(float(r.split()[6]) > 0 for r in rows if "waits" not in r)
    assert (
        "candidates: 8 runs" in text and "seeds: 8 runs" in text and "CPU-hours left" in text and "upper bound" in text
    )
    _fake_done(run_dir(plan, "vlstm", "zara1", "a", 0), 0.5, epochs=2)
    again = dry_run(plan, "candidates", data_dir=str(data_dir))  # rates come from the cache now
    assert "measured now" not in again
    assert any(" done " in line and line.startswith("candidates vlstm   zara1  a ") for line in again.splitlines())

    def minutes(text: str, prefix: str) -> float:  # the CPU-min column: the field before the command
        fields = next(line for line in text.splitlines() if line.startswith(prefix)).split()
        return float(fields[fields.index("crowdnav-mesrnn") - 1])

    # An epoch already trained with candidate a of vlstm (hotel, partial) replaces the short measurement:
    # at a rate 1000x the fastest measured one, the estimate for that run shrinks.
    import torch

    measured = json.loads((tmp_path / "runs" / "rates.json").read_text())
    before = minutes(again, "candidates vlstm   hotel  a ")
    partial = run_dir(plan, "vlstm", "hotel", "a", 0)
    partial.mkdir(parents=True)
    rate = 1000 * max(v["train_windows_per_s"] for v in measured.values())
    torch.save({"epoch": 1, "history": [{"epoch": 1, "windows_per_s": rate}]}, partial / "last.pt")
    after = dry_run(plan, "candidates", data_dir=str(data_dir))
    rate_line = next(line for line in after.splitlines() if line.startswith("  vlstm  a "))
    assert "over 1 epoch(s), used instead" in rate_line
    short = float(rate_line.split("train")[1].split()[0])
    trained = float(rate_line.split("trained so far:")[1].split()[0])
    assert trained > 50 * short  # 1000x, give or take hotel's window sizes against zara1's
    assert "epoch 1" in next(line for line in after.splitlines() if line.startswith("candidates vlstm   hotel  a "))
    assert minutes(after, "candidates vlstm   hotel  a ") <= before  # one epoch of two left, and faster
    assert minutes(after, "candidates srnn    hotel  a ") == pytest.approx(
        minutes(again, "candidates srnn    hotel  a ")
    )


def test_a_plan_with_export_false_never_ships(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "shipped")
    (tmp_path / "plan.yaml").write_text(
        f"models: [vlstm]\nsplits: [zara1]\nseeds: [0]\nout_dir: {tmp_path / 'runs'}\nexport: false\n"
        "candidates: {a: {config: 'configs/predictor/{model}.yaml'}}\n"
    )
    plan = load_plan(tmp_path / "plan.yaml")
    _fake_done(tmp_path / "runs" / "vlstm" / "zara1" / "a" / "seed0", 0.5)
    with pytest.raises(ConfigError, match="'export' is false"):
        execute(plan, "export")
    assert not (tmp_path / "shipped").exists()


def test_fixed_rotation_plan_reuses_the_comparison_runs() -> None:
    """The fixed-candidate plan trains every model with the comparison's ``residual_rotation`` candidate
    in the same run folders (so its seed-0 runs are the comparison's), and cannot ship weights."""
    fixed = load_plan(REPO_ROOT / "configs" / "predictor" / "fixed_rotation.yaml")
    main = load_plan(SHIPPED)
    assert not fixed.export and main.export
    (only,) = fixed.candidates
    assert only == next(c for c in main.candidates if c.name == only.name)
    assert (fixed.models, fixed.splits, fixed.seeds, fixed.out_dir) == (
        main.models,
        main.splits,
        main.seeds,
        main.out_dir,
    )
