"""The text of ``docs/results/predictors.md`` (and of a plan's page), rendered from the report's JSON
(:func:`crowdnav_mesrnn.studies.report.build_report`); every figure and verdict is read from it. The published
figures and the fixed prose of the page are constants here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.studies.claims.compute import COMMAND as CLAIMS_COMMAND
from crowdnav_mesrnn.studies.claims.render import render_claims

PUBLISHED_SGAN: dict[str, dict[str, tuple[float, float]]] = {
    "Linear": {
        "eth": (1.33, 2.94),
        "hotel": (0.39, 0.72),
        "univ": (0.82, 1.59),
        "zara1": (0.62, 1.21),
        "zara2": (0.77, 1.48),
        "average": (0.79, 1.59),
    },
    "LSTM": {
        "eth": (1.09, 2.41),
        "hotel": (0.86, 1.91),
        "univ": (0.61, 1.31),
        "zara1": (0.41, 0.88),
        "zara2": (0.52, 1.11),
        "average": (0.70, 1.52),
    },
    "Social-LSTM": {
        "eth": (1.09, 2.35),
        "hotel": (0.79, 1.76),
        "univ": (0.67, 1.40),
        "zara1": (0.47, 1.00),
        "zara2": (0.56, 1.17),
        "average": (0.72, 1.54),
    },
    "SGAN-1V-1": {
        "eth": (1.13, 2.21),
        "hotel": (1.01, 2.18),
        "univ": (0.60, 1.28),
        "zara1": (0.42, 0.91),
        "zara2": (0.52, 1.11),
        "average": (0.74, 1.54),
    },
}
COLS = (*SPLITS, "average")
#: Keys of the results that are not rows of the headline table.
SECTIONS = ("comparisons", "bootstrap", "seeds", "claims")

NAMES = {"cv": "CV", "vlstm": "VLSTM", "srnn": "SRNN", "mesrnn": "MESRNN"}
LABELS = {
    "cv": "Constant velocity",
    "vlstm": "VLSTM (shipped)",
    "srnn": "SRNN (shipped)",
    "mesrnn": "MESRNN (shipped)",
}
PLAN_FILE = "configs/predictor/candidates.yaml"

OPTIONS = """## Configurations: the paper's and the project's options

*Paper config* (`configs/predictor/{mesrnn,srnn,vlstm}.yaml`): node embedding 128, node hidden 256,
edge embedding 64, edge hidden 128; the node RNN reads the absolute (normalised) position; meta-paths
summed over neighbours; MSE on the 12 predicted steps with teacher forcing; Adam 1e-3, gradient norm
10, 10 epochs.

*Residual config* (`configs/predictor/{mesrnn,srnn,vlstm}_residual.yaml`), options added beside the
paper's, each a documented `ModelConfig`/`TrainConfig` key:
- `node_input: velocity` — the node RNN reads the last displacement instead of the absolute position,
  which is meaningless across scenes under leave-one-out;
- `offset: cv_residual` — the decoder's offset is added to a constant-velocity step and starts at zero,
  so the untrained network is exactly constant velocity and learns corrections to it;
- `teacher_forcing: false` — trained on its own 12-step rollout, exactly as evaluated;
- `aggregate: mean`, `standardise: true` — meta-paths averaged over neighbours and every feature type
  scaled to unit RMS on training data (the raw SS/TT products are orders of magnitude smaller than S);
- halved sizes, lr 3e-4 and 8 epochs;
- `augment_rotation: true` (the *residual_rotation* candidate) — each training window rotated by a
  random angle about its centre before normalising.
These change the inputs and the training, not the protocol: same windows, same rollout, same metric.

*The comparison* (`configs/predictor/candidates.yaml`, committed before its runs): the same candidate
set for VLSTM, SRNN and MESRNN; per (model, split) the candidate with the lowest validation ADE (the
`_val` pieces of the training scenes; test data never enter a choice) is trained with every seed; the
shipped weights are the seed with the lowest validation ADE. An earlier version of this page had given
only MESRNN the rotation-augmented candidate, added after test numbers had been seen; the plan replaces
that. Validation data are in-domain, so they cannot show how a model transfers to the held-out scene."""

FIGURES = """## Figures

Observed paths (black), true futures (green) and each model's forecast (dotted) for every scored
pedestrian of a test window, to scale (`crowdnav-mesrnn predictor plot --split SPLIT --window N`):

| sparse: zara1 window 336 | crowded: zara1 window 394 | very crowded: univ window 0 |
|---|---|---|
| ![](zara1_window_336.png) | ![](zara1_window_394.png) | ![](univ_window_0.png) |"""


def _row(label: str, res: dict[str, Any], a: str, f: str, fmt: str) -> str:
    cells = []
    for s in COLS:
        r = res["splits"].get(s)
        cells.append(f"{r[a]:{fmt}} / {r[f]:{fmt}}" if r else "–")
    return f"| {label} | " + " | ".join(cells) + " |"


def _label(key: str) -> str:
    return LABELS.get(key, f"{key.split(':')[0].upper()} ({key.split(':', 1)[-1]})")


def render_plan(results: dict[str, Any]) -> str:
    """The page of :func:`build_plan_report`."""
    seeds = results["seeds"]
    plan = seeds["plan"]
    cands = list(dict.fromkeys(c for row in seeds["rows"].values() for c in row.get("candidates_val_ade_m", {})))
    head = "| model | " + " | ".join(COLS) + " |\n|---|" + "---|" * len(COLS)
    lines = [
        f"# Predictor plan `{plan}`: test ADE / FDE over seeds",
        "",
        f"Generated by `crowdnav-mesrnn predictor report --plan {plan} --plan-only` (see *Reproduce*); do not edit",
        "by hand. True autoregressive rollouts on the test part of every split, as in",
        "[predictors.md](predictors.md), which describes the protocol and the shipped predictors.",
        f"Candidates: {', '.join(cands) or '–'}"
        + (" (one candidate: every model is trained with the same configuration)." if len(cands) == 1 else "."),
        "This plan "
        + ("may ship weights (`--stage export`)." if seeds.get("export", True) else "never ships weights."),
        "",
        "Constant velocity (ADE / FDE, metres):",
        "",
        head,
        _row("Constant velocity", results["cv"], "ade_m", "fde_m", ".3f"),
        "",
        *render_seeds(seeds),
        "",
        *render_comparisons(seeds.get("comparisons"), results["bootstrap"], n_seeds=len(seeds["seeds"])),
    ]
    chosen = {k: v for k, v in (seeds.get("comparisons") or {}).items() if "average" in v["ade_m"]}
    srnn_fde = _seeds_srnn_fde(seeds)
    lines += ["", "## Does the paper's ordering hold here?", "", "Read from the differences over seeds (ADE):", ""]
    lines += (
        ordering(chosen, {k: "over seeds" for k in chosen}, srnn_fde)
        if chosen
        else ["No five-split average yet: the plan covers fewer splits, or not every seed has finished."]
    )
    lines += candidate_confounds(seeds)
    lines += [
        "",
        "## Reproduce",
        "",
        "```bash",
        f"crowdnav-mesrnn predictor plan {plan} --dry-run   # every run and the CPU budget",
        f"crowdnav-mesrnn predictor plan {plan}             # train what is missing (resumable; --shard i/n)",
        f"crowdnav-mesrnn predictor report --plan {plan} --plan-only --out PAGE.md",
        "```",
    ]
    return "\n".join(lines) + "\n"


def _seeds_srnn_fde(seeds: dict[str, Any] | None) -> float | None:
    """SRNN's five-split average FDE over the plan's seeds (mean), where it has one."""
    return (((seeds or {}).get("average") or {}).get("srnn") or {}).get("fde_m", {}).get("mean")


# ------------------------------------------------------------------ rendering
def _ci_cell(d: dict[str, Any] | None) -> str:
    if d is None:
        return "–"
    lo, hi = d["ci"]
    return f"{d['diff']:+.3f} [{lo:+.3f}, {hi:+.3f}]"


def _pm(d: dict[str, Any], m: str) -> str:
    std = d[m]["std"]
    return f"{d[m]['mean']:.3f}" + (f" ± {std:.3f}" if std is not None else "")


def _shipped_protocol(results: dict[str, Any]) -> str:
    notes = [
        (model, split, (results[model].get("checkpoints") or {}).get(split) or {})
        for model in ("vlstm", "srnn", "mesrnn")
        for split in SPLITS
    ]
    by_plan = [f"{m}/{s}" for m, s, n in notes if isinstance(n, dict) and "plan " in str(n.get("note", ""))]
    if len(by_plan) == len(notes):
        return "All 15 shipped predictors were exported by the comparison plan (`predictor plan ... --stage export`)."
    if not by_plan:
        later = (
            "the sections on seeds below describe the plan's runs, which are not exported yet "
            "(`predictor plan ... --stage export`)"
            if results.get("seeds")
            else "the seed and plan sections below are empty until `predictor plan` has run and exported"
        )
        return (
            "**The shipped predictors predate the comparison plan**: they were selected under the earlier "
            f"protocol (the selection table at the end says among what), and the rows marked *shipped* describe them; {later}."
        )
    return (
        f"{len(by_plan)} of 15 shipped predictors were exported by the comparison plan ({', '.join(by_plan)}); "
        "the others predate it (selection table at the end)."
    )


def render(results: dict[str, Any]) -> str:
    head = "| model | " + " | ".join(COLS) + " |\n|---|" + "---|" * len(COLS)
    rows = [k for k in results if k not in SECTIONS]
    lines = [
        "# Trajectory prediction results (ETH/UCY, leave-one-out, 8 observed → 12 predicted)",
        "",
        "Generated by `crowdnav-mesrnn predictor report` (see *Reproduce* below); do not edit by hand.",
        "Every learned number is a true autoregressive rollout: after the last observation every input —",
        "the pedestrian's own position and every neighbour's in the meta-path features — is the model's",
        "own prediction. Scored pedestrians: present in all 20 steps, windows with at least 2 of them.",
        "",
        _shipped_protocol(results),
        "",
        "## ADE / FDE in metres (headline)",
        "",
        head,
    ]
    lines += [_row(_label(k), results[k], "ade_m", "fde_m", ".2f") for k in rows]
    lines += ["", "Published figures for orientation (Social-GAN paper, Table 1, same protocol, metres):", "", head]
    for name, vals in PUBLISHED_SGAN.items():
        lines.append(f"| {name} | " + " | ".join(f"{vals[s][0]:.2f} / {vals[s][1]:.2f}" for s in COLS) + " |")
    lines += ["", *render_seeds(results.get("seeds"))]
    seeds = results.get("seeds")
    if seeds:
        lines += ["", *render_comparisons(seeds.get("comparisons"), results["bootstrap"], n_seeds=len(seeds["seeds"]))]
    lines += ["", *render_comparisons(results["comparisons"], results["bootstrap"])]
    chosen, sources, source_line = _ordering_source(results)
    if sources.get("mesrnn-srnn") == "over seeds":
        srnn_fde = _seeds_srnn_fde(seeds)
    else:
        srnn_fde = (results.get("srnn", {}).get("splits", {}).get("average") or {}).get("fde_m")
    lines += ["", "## Does the paper's ordering hold?", "", source_line, "", *ordering(chosen, sources, srnn_fde)]
    lines += candidate_confounds(seeds)
    lines += ["", *render_claims(results.get("claims"))]
    lines += [
        "",
        "## ADE / FDE in the paper's min-max-normalised units",
        "",
        "Positions mapped to [-1, 1] per axis with the statistics of each split's training part (the metric",
        "of the MESRNN paper's Table I; smaller scenes look better in it, so it is not comparable across",
        "splits). The paper's Table I values were not available to this project's build and are not copied here.",
        "",
        head,
    ]
    lines += [_row(_label(k), results[k], "ade_norm", "fde_norm", ".4f") for k in rows]
    lines += ["", OPTIONS, "", FIGURES]
    lines += ["", "## Which configuration each shipped model uses (chosen on validation data only)", ""]
    lines += ["| model | split | selection |", "|---|---|---|", *_selection_rows(results)]
    lines += ["", "## Reproduce", "", *reproduce_rows(results), "", "```bash", REPRODUCE.rstrip(), "```"]
    return "\n".join(lines) + "\n"


def _selection_rows(results: dict[str, Any]) -> list[str]:
    rows = []
    for model in ("vlstm", "srnn", "mesrnn"):
        for split in SPLITS:
            sel = (results[model].get("checkpoints") or {}).get(split) or {}
            note = sel.get("note", "") if isinstance(sel, dict) else ""
            rows.append(f"| {model} | {split} | {note} |")
    return rows


def render_seeds(seeds: dict[str, Any] | None) -> list[str]:
    """The seeds section: test ADE / FDE mean ± std over the seeds of each selected candidate."""
    lines = ["## Seeds of the selected configurations (test ADE / FDE, metres, mean ± std over seeds)", ""]
    if not seeds:
        return [
            *lines,
            f"Not computed: run `crowdnav-mesrnn predictor report --plan {PLAN_FILE}` after the plan's runs.",
        ]
    head = "| model | " + " | ".join(COLS) + " |\n|---|" + "---|" * len(COLS)
    lines += [
        f"Seeds {seeds['seeds']} of the candidate each (model, split) uses, selected on validation data where the plan "
        f"has several (plan `{seeds['plan']}`);",
        "cells: ADE / FDE; n = finished seeds.",
        "",
        head,
    ]
    for model in ("vlstm", "srnn", "mesrnn"):
        cells = []
        for s in SPLITS:
            row = seeds["rows"].get(f"{model}/{s}")
            t = (row or {}).get("test")
            cells.append(f"{_pm(t, 'ade_m')} / {_pm(t, 'fde_m')} (n={t['n']})" if t else "–")
        avg = seeds["average"].get(model)
        cells.append(f"{_pm(avg, 'ade_m')} / {_pm(avg, 'fde_m')} (n={avg['n']})" if avg else "–")
        lines.append(f"| {NAMES[model]} | " + " | ".join(cells) + " |")
    best = "shipped seed" if seeds.get("export", True) else "best val seed (not shipped)"
    lines += [
        "",
        f"| model | split | candidates (val ADE, m) | selected | seeds (val ADE, m) | {best} |",
        "|---|---|---|---|---|---|",
    ]
    for key, row in seeds["rows"].items():
        model, split = key.split("/")
        cands = ", ".join(f"{c} {v:.3f}" for c, v in row["candidates_val_ade_m"].items()) or "–"
        seed_vals = ", ".join(f"{k}: {v['val_ade_m']:.3f}" for k, v in row["seeds"].items()) or "–"
        lines.append(
            f"| {model} | {split} | {cands} | {row['selected'] or '–'} | {seed_vals} | {row.get('shipped_seed', '–')} |"
        )
    return [*lines, "", *render_candidates_test(seeds)]


def render_candidates_test(seeds: dict[str, Any]) -> list[str]:
    """Every candidate's selection-seed run on test: for orientation only, marked where selected."""
    rows = seeds["rows"]
    names = list(dict.fromkeys(c for row in rows.values() for c in row.get("candidates_val_ade_m", {})))
    if len(names) < 2 or not any(row.get("candidates_test") for row in rows.values()):
        return []  # one candidate: its seed runs above are the whole story
    head = "| model | candidate | " + " | ".join(COLS) + " |\n|---|---|" + "---|" * len(COLS)
    lines = [
        "Every candidate on test (ADE / FDE, metres; the run of the selection seed). For orientation",
        "only: the choice was made on validation ADE before these were computed; * marks the candidate",
        "selected on that split. The *paper* rows are the paper's configuration on every split.",
        "",
        head,
    ]
    for model in ("vlstm", "srnn", "mesrnn"):
        for name in names:
            cells, ades, fdes = [], [], []
            for s in SPLITS:
                row = rows.get(f"{model}/{s}") or {}
                t = (row.get("candidates_test") or {}).get(name)
                if t is None:
                    cells.append("–")
                    continue
                ades.append(t["ade_m"])
                fdes.append(t["fde_m"])
                cells.append(f"{t['ade_m']:.3f} / {t['fde_m']:.3f}" + (" *" if row.get("selected") == name else ""))
            cells.append(f"{np.mean(ades):.3f} / {np.mean(fdes):.3f}" if len(ades) == len(SPLITS) else "–")
            if ades:
                lines.append(f"| {NAMES[model]} | {name} | " + " | ".join(cells) + " |")
    return lines


def render_comparisons(
    comparisons: dict[str, Any] | None, boot: dict[str, Any], n_seeds: int | None = None
) -> list[str]:
    """The table of paired differences: of the shipped predictors, or (``n_seeds`` given) over the
    plan's seeds."""
    head = "| difference | " + " | ".join(COLS) + " |\n|---|" + "---|" * len(COLS)
    if n_seeds is not None:
        lines = [
            "## Paired differences over seeds, with 95 % intervals over windows and seeds",
            "",
            f"The same comparisons between seed-averaged errors: the {n_seeds} seeds of the configuration each",
            "(model, split) uses, selected on validation where the plan has several candidates (constant velocity",
            "has one seed). The interval adds two sources:",
            "the test windows (variance of the block bootstrap below, applied to the seed-averaged difference)",
            "and the training seeds (each model's per-seed errors: s²/S, with Welch-Satterthwaite degrees of",
            f"freedom; {n_seeds} seeds against constant velocity give at least {n_seeds - 1}). Resampling so few seeds",
            "instead would be far too narrow. The five-split average takes each seed's mean over the splits.",
            "These intervals are conditional on the selected configuration: the choice of candidate, made",
            "with one seed, is not resampled. The ordering below is read from this table where it is complete.",
        ]
        if comparisons is None:
            return [*lines, "", "Not computed: these results predate the comparison over seeds; re-run the report."]
        if not comparisons:
            return [*lines, "", "Not computed: no (model, split) has all its seeds finished."]
    else:
        lines = [
            "## Paired differences with 95 % intervals (shipped predictors)",
            "",
            "Each cell: A − B in metres over the same test windows and pedestrians (negative: A is better)",
            "and a 95 % percentile interval from a moving-block bootstrap over consecutive test windows. Test",
            f"windows slide by one step and overlap, so blocks of {boot['block_len_windows']} consecutive windows "
            "(the window length in steps)",
            f"are resampled, {boot['resamples']} times; the average column resamples the five splits",
            "independently. An interval that includes 0 reads *no detectable difference*. One trained seed",
            "per model: these intervals do not include seed-to-seed variation.",
        ]
    for metric, name in (("ade_m", "ADE"), ("fde_m", "FDE")):
        lines += ["", f"{name} difference, metres:", "", head]
        for key, entry in comparisons.items():
            a, b = key.split("-")
            lines.append(
                f"| {NAMES[a]} − {NAMES[b]} | " + " | ".join(_ci_cell(entry[metric].get(c)) for c in COLS) + " |"
            )
    lines += ["", "Verdicts (ADE):", "", "| comparison | " + " | ".join(COLS) + " |\n|---|" + "---|" * len(COLS)]
    for key, entry in comparisons.items():
        a, b = key.split("-")
        cells = [entry["ade_m"].get(c, {}).get("verdict", "–") for c in COLS]
        lines.append(f"| {NAMES[a]} vs {NAMES[b]} | " + " | ".join(cells) + " |")
    return lines


def _ordering_source(results: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str], str]:
    """Per pair, the comparison over seeds where it has its five-split average, else the shipped
    predictors'; and a line saying which and why."""
    seeds = results.get("seeds")
    seeded = (seeds or {}).get("comparisons") or {}
    chosen: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for key, entry in results["comparisons"].items():
        over = seeded.get(key)
        if over is not None and "average" in over["ade_m"]:
            chosen[key], sources[key] = over, "over seeds"
        else:
            chosen[key], sources[key] = entry, "shipped predictors, one seed each"
    if all(v == "over seeds" for v in sources.values()):
        return chosen, sources, "Read from the differences over seeds (ADE):"
    if not seeds:
        why = "the report was run without `--plan`"
    else:
        why = "not every seed of the plan has finished on all five splits"
    return chosen, sources, f"Read, where marked, from the shipped predictors (one seed each) because {why} (ADE):"


def ordering(
    comparisons: dict[str, Any], sources: dict[str, str] | None = None, srnn_fde: float | None = None
) -> list[str]:
    """Plain statements read from the intervals (ADE): never a win where the interval includes 0;
    ``sources`` names, per pair, which comparison a line was read from; ``srnn_fde`` (SRNN's average
    FDE in the same comparison) puts the MESRNN − SRNN FDE difference beside the paper's claim."""
    out = []

    def summary_line(a: str, b: str) -> str | None:
        entry = comparisons.get(f"{a}-{b}")
        if entry is None:
            return None
        per = entry["ade_m"]
        groups: dict[str, list[str]] = {}
        for s in SPLITS:
            if s in per:
                groups.setdefault(per[s]["verdict"], []).append(s)
        parts = [f"{v} on {', '.join(ss)}" for v, ss in groups.items()]
        avg = per.get("average")
        head = f"average ADE difference {_ci_cell(avg)} m → **{avg['verdict']}**" if avg else "no five-split average"
        src = f" ({sources[f'{a}-{b}']})" if sources and f"{a}-{b}" in sources else ""
        return f"- {NAMES[a]} − {NAMES[b]}{src}: {head}; per split: {'; '.join(parts)}."

    for a, b in (("mesrnn", "srnn"), ("srnn", "vlstm"), ("mesrnn", "cv"), ("srnn", "cv"), ("vlstm", "cv")):
        line = summary_line(a, b)
        if line:
            out.append(line)
    ms, sv = comparisons.get("mesrnn-srnn", {}), comparisons.get("srnn-vlstm", {})
    avg = [c.get("ade_m", {}).get("average") for c in (ms, sv)]
    if all(avg):
        hi = [a["ci"][1] for a in avg]
        lo = [a["ci"][0] for a in avg]
        if all(h < 0 for h in hi):
            state = "**holds** (both average differences detectably negative)"
        elif any(x > 0 for x in lo):
            state = "**is contradicted** (a difference is detectably in the other direction)"
        else:
            state = "**is not established** (at least one average difference is not detectable)"
        out.append(f"- The paper's ordering MESRNN < SRNN < VLSTM (average ADE) {state}.")
    fde = comparisons.get("mesrnn-srnn", {}).get("fde_m", {}).get("average")
    line = "- The paper reports MESRNN over 32 % better than SRNN at long horizons"
    if fde is not None and srnn_fde:
        line += (
            f"; here the average FDE difference MESRNN − SRNN is {_ci_cell(fde)} m, "
            f"{100 * -fde['diff'] / srnn_fde:.0f} % of SRNN's {srnn_fde:.3f} m."
        )
    else:
        line += "; compare the MESRNN − SRNN row."
    out.append(line)
    return out


def candidate_confounds(seeds: dict[str, Any] | None) -> list[str]:
    """Where two compared models were selected with different candidates, their difference there is
    partly the candidate's, not the architecture's: name those splits."""
    if not seeds:
        return []
    rows = seeds["rows"]
    out = []
    for a, b in (("mesrnn", "srnn"), ("srnn", "vlstm"), ("mesrnn", "vlstm")):
        diff = [
            f"{s} ({rows[f'{a}/{s}']['selected']} vs {rows[f'{b}/{s}']['selected']})"
            for s in SPLITS
            if rows.get(f"{a}/{s}", {}).get("selected") is not None
            and rows.get(f"{b}/{s}", {}).get("selected") is not None
            and rows[f"{a}/{s}"]["selected"] != rows[f"{b}/{s}"]["selected"]
        ]
        if diff:
            out.append(
                f"- {NAMES[a]} and {NAMES[b]} were selected with different candidates on {', '.join(diff)}: "
                "there their difference may be partly the candidate's, not the architecture's. The test table of "
                "every candidate above (one seed, orientation only) is suggestive, not evidence."
            )
    return out


def reproduce_rows(results: dict[str, Any]) -> list[str]:
    """One reproduce command per row of the headline table (and where its weights came from)."""
    lines = ["| row | evaluate | weights from |", "|---|---|---|"]
    for key in results:
        if key in SECTIONS:
            continue
        if key == "cv":
            lines.append("| Constant velocity | `crowdnav-mesrnn predictor eval --model cv --split all` | – |")
        elif key in NAMES:
            notes = [
                str(n.get("note", "")) for n in (results[key].get("checkpoints") or {}).values() if isinstance(n, dict)
            ]
            by_plan = bool(notes) and all("plan " in n for n in notes)
            source = (
                f"`crowdnav-mesrnn predictor plan {PLAN_FILE}` then `--stage export`"
                if by_plan
                else "earlier protocol: `crowdnav-mesrnn predictor train --model "
                f"{key} --split SPLIT --config configs/predictor/{key}_residual.yaml` (runs named *rotaug* in the "
                "selection table: plus `--set augment_rotation=true`)"
            )
            lines.append(f"| {_label(key)} | `crowdnav-mesrnn predictor eval --model {key} --split all` | {source} |")
        else:
            model = key.split(":")[0]
            trained = results[key].get("trained_by")
            lines.append(
                f"| {_label(key)} | `crowdnav-mesrnn predictor eval --model {model} --split all "
                f"--checkpoint '{results[key].get('template', '?')}'` | "
                + (f"`{trained}` (for each split)" if trained else "no run.yaml beside the checkpoint")
                + " |"
            )
    lines.append(
        f"| Seeds, intervals, verdicts | `crowdnav-mesrnn predictor report --plan {PLAN_FILE}` | "
        f"`crowdnav-mesrnn predictor plan {PLAN_FILE}` |"
    )
    lines.append(
        f"| The paper's further claims | `{CLAIMS_COMMAND}` (or the whole report) | the shipped weights, "
        "or the plan's seeds where its run folders hold them all |"
    )
    return lines


REPRODUCE = f"""\
# the comparison, declared in {PLAN_FILE}: every candidate x model x split, then the seeds of the
# candidate each (model, split) selects on validation data; resumable (finished runs are skipped)
crowdnav-mesrnn predictor plan {PLAN_FILE} --dry-run              # every run and the CPU budget
crowdnav-mesrnn predictor plan {PLAN_FILE} --shard 0/2 &          # one process per core
crowdnav-mesrnn predictor plan {PLAN_FILE} --shard 1/2
crowdnav-mesrnn predictor plan {PLAN_FILE}                        # again, until nothing is left
crowdnav-mesrnn predictor plan {PLAN_FILE} --stage export         # ship the best-validation seeds
# this page (evaluates the shipped weights, the plan's seeds and any --extra rows; the claims section too)
crowdnav-mesrnn predictor report --plan {PLAN_FILE} --out docs/results/predictors.md
# the claims section alone, added to the existing page and its JSON (nothing else re-evaluated)
{CLAIMS_COMMAND}
# any single row
crowdnav-mesrnn predictor eval --model mesrnn --split all
"""
