"""The Markdown summary (``summary.md``) of the ablation."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from agents.ablation.cells import _hms
from agents.ablation.config import AblationConfig

#: Small counts as running text writes them.
_NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


def _count(n: int) -> str:
    """``n`` in words up to ten (as running text writes it), in digits beyond."""
    return _NUMBER_WORDS[n] if 0 <= n < len(_NUMBER_WORDS) else str(n)


def _pct(rate: Any, ci: Any) -> str:
    if rate is None:
        return "-"
    lo, hi = ci if ci else (None, None)
    bounds = f" [{100 * lo:.1f}, {100 * hi:.1f}]" if lo is not None and hi is not None else ""
    return f"{100 * rate:.1f}{bounds}"


def _mean(entry: Mapping[str, Any], metric: str, digits: int = 2, missing: str = "-") -> str:
    """``mean [lo, hi]`` of ``entry``'s ``<metric>_mean`` and ``<metric>_ci``; ``missing`` when there is none."""
    v = entry.get(f"{metric}_mean")
    if v is None:
        return missing
    lo, hi = entry.get(f"{metric}_ci") or (None, None)
    bounds = f" [{lo:.{digits}f}, {hi:.{digits}f}]" if lo is not None and hi is not None else ""
    return f"{v:.{digits}f}{bounds}"


#: Columns of the rate tables after the rates: (header, metric, digits). The metrics of issue 31 replace or join
#: the older ones only where the episodes record them (summaries of older archives render as they did).
_METRIC_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("nav. time s (successes)", "navigation_time_s", 1),
    ("path ratio (successes)", "path_ratio", 2),
    ("min gap m", "min_gap_m", 2),
    ("forecast ADE m", "forecast_ade_m", 2),
)
_CURRENT_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("nav. time s (successes)", "navigation_time_s", 1),
    ("path ratio to required (successes)", "path_ratio_required", 2),
    ("SPL", "spl", 2),
    ("min clearance m", "min_clearance_m", 2),
    ("min TTC s", "min_ttc_s", 2),
    ("forecast ADE m", "forecast_ade_m", 2),
)


def _columns(entries: Mapping[str, Mapping[str, Any]]) -> tuple[tuple[str, str, int], ...]:
    """The current columns when any entry records the metrics of issue 31 (``spl``), else the older ones."""
    return _CURRENT_COLUMNS if any("spl_mean" in e for e in entries.values()) else _METRIC_COLUMNS


def _rate_table(entries: Mapping[str, Mapping[str, Any]], with_seeds: bool) -> list[str]:
    columns = _columns(entries)
    head = "| arm | " + ("seeds | " if with_seeds else "") + "episodes | success % | collision % | timeout % | "
    head += " | ".join(h for h, _, _ in columns) + " |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for arm, e in entries.items():
        seeds = (", ".join(map(str, e.get("seeds", []))) + " | ") if with_seeds else ""
        means = " | ".join(_mean(e, key, digits) for _, key, digits in columns)
        lines.append(
            f"| {arm} | {seeds}{e['episodes']} | {_pct(e['success_rate'], e['success_ci'])} | "
            f"{_pct(e['collision_rate'], e['collision_ci'])} | {_pct(e['timeout_rate'], e['timeout_ci'])} | "
            f"{means} |"
        )
    return lines


def _p(v: Any) -> str:
    if v is None:
        return "-"
    return f"{v:.2g}" if v < 0.001 else f"{v:.3f}"


def _ceiling_lines(summary: Mapping[str, Any]) -> list[str]:
    """The section of success as a fraction of the privileged ceiling (nothing when the grid has none); a grid with
    several (one per reaction) has one table each, dividing the policies in the same environment."""
    ceilings = summary.get("ceilings") or [summary.get("ceiling")]
    if not ceilings[0]:
        return []
    lines = ["## Fraction of the privileged ceiling", ""]
    for ceiling in ceilings:
        splits = [sp for sp in summary["splits"] if sp in ceiling["by_split"]]
        rates = ", ".join(f"{sp} {100 * ceiling['by_split'][sp]:.1f} %" for sp in splits)
        reads = (
            "rolls the reaction model forward for every candidate plan (the pedestrians' replies to the robot)"
            if ceiling.get("reactive")
            else "reads the replay's true future of every pedestrian"
        )
        lines += [
            f"`{ceiling['policy']}` is PRIVILEGED: it {reads}, which no "
            f"policy's observation carries -- a measuring stick, not a competitor. Its success: {rates}. Each cell "
            "below is a policy's success divided by the ceiling's on the same episodes (pooled over seeds).",
            "",
            "| policy | arm | " + " | ".join(splits) + " |",
            "|---|---" + "|---" * len(splits) + "|",
        ]
        for name, arms in ceiling["fractions"].items():
            for arm, by_split in arms.items():
                cells = [f"{by_split[sp]:.3f}" if by_split.get(sp) is not None else "-" for sp in splits]
                lines.append(f"| {name} | {arm} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _avoidable_lines(summary: Mapping[str, Any]) -> list[str]:
    """Each policy's failures classed by its environment's privileged ceiling (grids with a ceiling per reaction)."""
    entries = summary.get("avoidable_failures") or []
    if not entries:
        return []
    lines = [
        "## Failures the ceiling avoided",
        "",
        "A policy's failure (collision or timeout) in an episode its environment's PRIVILEGED ceiling succeeded in was "
        "avoidable (under the reaction model, a clear way existed); one the ceiling failed too is not shown avoidable "
        "(the ceiling's beam search is not complete: not proven unavoidable). Counts over the episodes of every split; "
        "per split: avoidable / failures.",
        "",
    ]
    for entry in entries:
        splits = [sp for sp in summary["splits"] if sp in entry["ceiling_failures"]]
        fails = ", ".join(f"{sp} {entry['ceiling_failures'][sp]}" for sp in splits)
        lines += [
            f"`{entry['policy']}` failed in: {fails} episode(s).",
            "",
            "| policy | arm | failures | avoidable | not shown avoidable | " + " | ".join(splits) + " |",
            "|---|---|---:|---:|---:" + "|---" * len(splits) + "|",
        ]
        for name, arms in entry["classes"].items():
            for arm, c in arms.items():
                share = f" ({100 * c['avoidable'] / c['failures']:.0f} %)" if c["failures"] else ""
                per = [
                    f"{c['by_split'][sp]['avoidable']} / {c['by_split'][sp]['failures']}"
                    if sp in c["by_split"]
                    else "-"
                    for sp in splits
                ]
                unmatched = f" (+{c['unmatched']} unmatched)" if c["unmatched"] else ""
                lines.append(
                    f"| {name} | {arm} | {c['failures']}{unmatched} | {c['avoidable']}{share} | "
                    f"{c['not_shown_avoidable']} | " + " | ".join(per) + " |"
                )
        lines.append("")
    return lines


def _points(value: Any, ci: Any = None) -> str:
    """A difference of rates in percentage points, signed, with its interval."""
    if value is None:
        return "-"
    lo, hi = ci if ci else (None, None)
    bounds = f" [{100 * lo:+.1f}, {100 * hi:+.1f}]" if lo is not None and hi is not None else ""
    return f"{100 * value:+.1f}{bounds}"


def _value(value: Any, ci: Any = None, digits: int = 2, sign: bool = False) -> str:
    if value is None:
        return "-"
    lo, hi = ci if ci else (None, None)
    fmt = f"{'+' if sign else ''}.{digits}f"
    bounds = f" [{lo:{fmt}}, {hi:{fmt}}]" if lo is not None and hi is not None else ""
    return f"{value:{fmt}}{bounds}"


def _test_rows(
    tests: Sequence[Mapping[str, Any]],
    head: Callable[[Mapping[str, Any]], str],
    body: Callable[[Mapping[str, Any]], str],
) -> list[str]:
    """Table rows of tests: ``head`` (the first cells, ``| a | b |``) then ``body``'s cells with the Holm-adjusted p
    starred when significant, or ``missing`` for a test whose cells have not run."""
    rows = []
    for t in tests:
        if t.get("missing"):
            rows.append(f"{head(t)} missing |")
            continue
        star = " *" if t.get("significant") else ""
        rows.append(f"{head(t)} {body(t)} | {_p(t['p_value'])} | {_p(t['p_holm'])}{star} |")
    return rows


def _reaction_lines(summary: Mapping[str, Any]) -> list[str]:
    """The section on reacting crowds (policies keyed ``<planner>@<reaction>``; nothing in a grid without them): success
    per planner, arm and reaction, the change of each gain across reactions, and what the robot did to people."""
    reacting = {n: p for n, p in summary["policies"].items() if p.get("reaction")}
    if not reacting:
        return []
    reactions = list(dict.fromkeys(p["reaction"] for p in reacting.values()))
    lines = [
        "## Reacting crowds",
        "",
        "A policy keyed `<planner>@<reaction>` ran among pedestrians who react to the robot (the environment's "
        "`reaction`, docs/reaction.md: each follows its recording until the robot comes near, reacts through the "
        "model, and rejoins its recording); `@none` is the replay. Every reaction runs the same fixed episodes. "
        "`oracle` is the recorded future, what people would have done without the robot: once they react it is a "
        "counterfactual, not the truth.",
        "",
        "Success % [95 % Wilson interval], pooled over the splits:",
        "",
        "| planner | arm | " + " | ".join(reactions) + " |",
        "|---|---" + "|---" * len(reactions) + "|",
    ]
    for planner in dict.fromkeys(n.split("@", 1)[0] for n in reacting):
        by_reaction = {p["reaction"]: p for n, p in reacting.items() if n.split("@", 1)[0] == planner}
        for arm in dict.fromkeys(a for p in by_reaction.values() for a in p["arms"]):
            entries = [by_reaction.get(r, {}).get("arms", {}).get(arm) for r in reactions]
            cells = [_pct(e["success_rate"], e["success_ci"]) if e else "" for e in entries]
            lines.append(f"| {planner} | {arm} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines + _gain_change_lines(summary) + _disturbance_lines(summary, reacting)


def _gain_change_lines(summary: Mapping[str, Any]) -> list[str]:
    """The declared change of each gain across reactions (``reaction_tests``), pooled and per split."""
    tests = summary.get("reaction_tests") or []
    if not tests:
        return []
    fam = summary["multiple_comparisons"]["family_sizes"].get("success_gain_change", 0)

    def head(t: Mapping[str, Any]) -> str:
        return f"| {t['planner']} | {t['gain']['a']} - {t['gain']['b']} | {t['reaction']} vs {t['baseline']} |"

    def body(t: Mapping[str, Any]) -> str:
        counts = " / ".join(str(t["d_counts"].get(str(k), 0)) for k in (-2, -1, 0, 1, 2))
        gains = f"{_points(t['gain_reaction'], t['gain_reaction_ci'])} | {_points(t['gain_baseline'], t['gain_baseline_ci'])}"
        return f"{t['n']} | {gains} | {_points(t['difference'], t['difference_ci'])} | {counts}"

    lines = [
        "### Does a forecast's gain survive when people react?",
        "",
        "A gain is `a - b`, the difference in success of two arms on the same episodes (points). Declared in the config "
        "before any result: for each planner run under both reactions and each arm comparison, the change of the gain "
        "from the baseline reaction to the reaction, on the same episodes pooled over the splits: per episode "
        "`d = (s_a,r - s_b,r) - (s_a,baseline - s_b,baseline)` in {-2, ..., 2} (`s` = 1 for a success), the change = "
        "mean `d` with a bootstrap percentile interval over episodes; exact sign-flip test of `d` (H0: `d` symmetric "
        f"about 0, the McNemar null generalised), Holm-Bonferroni over the {fam} tests; significant = Holm-adjusted "
        f"p <= {summary['multiple_comparisons']['alpha']}. A negative change: the gain shrinks where people react; the "
        "counts of `d` say how many episodes moved each way.",
        "",
        "| planner | gain | reaction vs baseline | episodes | gain there [95 % CI] | gain at baseline [95 % CI] | "
        "change [95 % CI] | d = -2 / -1 / 0 / +1 / +2 | p | p Holm |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *_test_rows(tests, head, body),
        "",
        "Per split (descriptive: the same estimate and test on each split's episodes, not in the Holm family):",
        "",
        "| planner | gain | reaction vs baseline | split | episodes | change [95 % CI] | p (unadjusted) |",
        "|---|---|---|---|---|---|---|",
    ]
    for t in tests:
        for split, e in ({} if t.get("missing") else t["by_split"]).items():
            change = _points(e["difference"], e["difference_ci"])
            lines.append(f"{head(t)} {split} | {e['n']} | {change} | {_p(e['p_value'])} |")
    return [*lines, ""]


def _disturbance_lines(summary: Mapping[str, Any], reacting: Mapping[str, Any]) -> list[str]:
    """The disturbance metrics per reacting policy and arm, and the declared comparisons (``disturbance_tests``)."""
    from agents.rollout import DISTURBANCE_METRICS

    lines: list[str] = []
    shown = {n: p for n, p in reacting.items() if any("ped_disturbed_mean" in e for e in p["arms"].values())}
    if shown:
        lines += [
            "### What the robot does to people",
            "",
            "Per episode, measured against the recordings (docs/reaction.md): `ped_disturbed` pedestrians that "
            "deviated from their recording, their mean and largest deviation (m), `ped_delay_s` the time they still "
            "needed beyond the recording (summed). Means over every episode of the arm (0 where nobody was disturbed; "
            "0 by definition under `none`) with 95 % bootstrap percentile intervals, which stay within the metric's "
            "range; disturbed = episodes that disturbed anyone (% with Wilson interval).",
            "",
            "| policy | arm | episodes | disturbed % | pedestrians disturbed | deviation mean m | deviation max m | "
            "delay s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, pol in shown.items():
            for arm, e in ((a, e) for a, e in pol["arms"].items() if "ped_disturbed_mean" in e):
                rate = _pct(e.get("disturbed_episode_rate"), e.get("disturbed_episode_ci"))
                metrics = " | ".join(_value(e.get(f"{m}_mean"), e.get(f"{m}_ci")) for m in DISTURBANCE_METRICS)
                lines.append(f"| {name} | {arm} | {e['episodes']} | {rate} | {metrics} |")
        lines.append("")
    tests = summary.get("disturbance_tests") or []
    if tests:
        fam = summary["multiple_comparisons"]["family_sizes"]
        sizes = ", ".join(f"{fam.get(m, 0)} for `{m}`" for m in DISTURBANCE_METRICS)
        lines += [
            "### Does planning with forecasts disturb people less?",
            "",
            "Declared in the config before any result: arm comparisons within every policy whose pedestrians react, "
            "on the episodes both arms finished successfully (the same trip completed), pooled over the splits: "
            "means of both arms, the mean difference a - b with a bootstrap percentile interval over pairs, and the "
            f"Wilcoxon signed-rank test, Holm-Bonferroni within each metric ({sizes}). Negative: arm a disturbs less.",
            "",
            "| policy | a | b | metric | pairs | mean a | mean b | a - b [95 % CI] | p | p Holm |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *_test_rows(
                tests,
                lambda t: f"| {t['policy']} | {t['a']} | {t['b']} | {t['endpoint']} |",
                lambda t: (
                    f"{t['pairs']} | {_value(t['mean_a'])} | {_value(t['mean_b'])} | "
                    f"{_value(t['difference'], t['difference_ci'], sign=True)}"
                ),
            ),
            "",
        ]
    return lines


def summary_markdown(summary: Mapping[str, Any], cfg: AblationConfig, figures: Sequence[str] = ()) -> str:
    """The human-readable report of :func:`summarize`."""
    lines = [f"# Ablation `{summary['name']}`", ""]
    if cfg.description:
        lines += [cfg.description.strip(), ""]
    pilot = summary.get("evaluation_episodes")  # absent when the cells replay the held-out scenes
    where = f"Held-out splits {', '.join(summary['splits'])}" if pilot is None else f"Episodes: {pilot['description']}"
    lines += [
        f"Config `{summary['config']}`, code {summary['code_version']}, generated {summary['generated']}. "
        f"{where}; {summary['episodes_per_cell']} evaluation episodes per "
        f"cell (episode list seed {summary['evaluation_seed']}, the same list in every cell of a split).",
        "",
    ]
    if pilot is not None:
        lines += [
            "**Validation episodes, not a held-out result:** every cell below replayed the training scenes of its "
            "split in their validation period (no held-out scene); use these figures for choices only.",
            "",
        ]
    if not summary["complete"]:
        lines += [
            f"**Incomplete:** {len(summary['missing_cells'])} cell(s) not finished; tables cover finished cells only.",
            "",
        ]
    lines += ["## Training budget and wall time", ""]
    for name, pol in summary["policies"].items():
        if pol["timesteps"]:
            lines.append(
                f"- `{name}` ({pol['kind']}): {pol['timesteps']:,} environment steps per run, {pol['n_envs']} "
                f"environments, agent config `{pol['agent_config']}`, evaluated with its {pol['model']} model; "
                f"seeds {', '.join(map(str, summary['seeds']))}."
            )
        else:
            lines.append(f"- `{name}` ({pol['kind']}): not trained; deterministic, evaluated once per arm and split.")
    wall = summary["wall_time"]
    cells = wall["cells_s"]
    lines += [
        f"- Compute in finished cells: training {_hms(cells.get('train', 0.0))}, evaluation "
        f"{_hms(cells.get('eval', 0.0))} (sum over cells). Grid wall time "
        + (
            f"{_hms(wall['span_s'])}, from the first cell's start ({wall['first_start']}) to the last cell's end "
            f"({wall['last_finish']}), pauses between sessions included."
            if wall.get("span_s") is not None
            else "unknown (no timings recorded)."
        ),
        "",
        "## Rates per policy and arm (pooled over splits and seeds)",
        "",
        "Rates in % with 95 % Wilson intervals; means with 95 % bootstrap intervals. Navigation time and path "
        "ratio average successful episodes only; the forecast ADE is closed-loop (forecasts made during the "
        "episodes, scored against the replay).",
        "",
    ]
    seeded_by_episode = sorted(
        name for name, pol in summary["policies"].items() if any("intervals" in e for e in pol["arms"].values())
    )
    if seeded_by_episode:
        lines += [
            "Intervals of "
            + ", ".join(f"`{n}`" for n in seeded_by_episode)
            + " (training seeds; here and in the density tables): a 95 % percentile bootstrap over episodes, each "
            "resampled with all its seeds' rows, around the pooled estimate. The seeds replay the same episodes, and an "
            "episode hard for one seed tends to be hard for the others, so an interval over rows would be too narrow. "
            "They do not count the variance between training seeds (the seed-level tests below do).",
            "",
        ]
    if any(_columns(pol["arms"]) is _CURRENT_COLUMNS for pol in summary["policies"].values()):
        lines += [
            "Path ratio to required: path length / (straight line - goal tolerance), at least 1 for a success. SPL: "
            "success weighted by path length (Anderson et al. 2018), over all episodes. Min clearance: closest "
            "surface distance to a pedestrian (0 at contact). Min TTC: smallest constant-velocity time to collision "
            "with a pedestrian, averaged over the episodes that had one on a collision course. Definitions: "
            "docs/env.md, episode metrics.",
            "",
        ]
    for name, pol in summary["policies"].items():
        lines += [f"### {name}", "", *_rate_table(pol["arms"], bool(pol["timesteps"])), ""]
        partial = sorted({m for e in pol["arms"].values() for m in e.get("metrics_partly_recorded", ())})
        if partial:
            lines += [
                "'-' above in a pooled row for "
                + ", ".join(f"`{m}`" for m in partial)
                + ": some of the arm's cells were written before these metrics existed (cells reused from an older "
                "grid's archive), so a pooled mean would cover only the splits that record them; the per-split tables "
                "below show them where recorded.",
                "",
            ]
        for split in summary["splits"] if len(summary["splits"]) > 1 else ():
            per = {a: e["by_split"][split] for a, e in pol["arms"].items() if split in e.get("by_split", {})}
            if per:
                lines += [f"{name} on `{split}`:", "", *_rate_table(per, False), ""]
    lines += _ceiling_lines(summary)
    lines += _avoidable_lines(summary)
    lines += _reaction_lines(summary)
    edges = summary["density_bins"]
    if edges:
        lines += [
            "## Success by crowd density",
            "",
            "Crowd density = mean number of pedestrians within sensor range of the straight start-goal segment "
            "over the episode (policy-independent); bins: "
            + ", ".join(f"[{lo:.2f}, {hi:.2f}]" for lo, hi in itertools.pairwise(edges))
            + ".",
            "",
        ]
        for name, pol in summary["policies"].items():
            head = "| arm | " + " | ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in itertools.pairwise(edges))
            lines += [f"{name}: success % [95 % CI] (episodes)", "", head + " |", "|---" * len(edges) + "|"]
            for arm, e in pol["arms"].items():
                cells_txt = [f"{_pct(r['success_rate'], r['success_ci'])} ({r['episodes']})" for r in e["by_density"]]
                lines.append(f"| {arm} | " + " | ".join(cells_txt) + " |")
            lines.append("")
    mc = summary["multiple_comparisons"]
    fam = mc["family_sizes"]
    against_fixed = any(t.get("test", "").startswith("exact sign-flip") for t in summary["tests"])
    by_episode = mc.get("test_unit") == "episode"
    lines += [
        "## Paired tests",
        "",
        f"Declared in the config before any result: arm comparisons {', '.join(f'{a} vs {b}' for a, b in cfg.comparisons) or '(none declared)'} "
        f"within each policy and split; policy comparisons {', '.join(f'{a} vs {b}' for a, b in cfg.policy_comparisons) or '(none declared)'} "
        "within each arm and split. "
        + (
            "The unit of every success and navigation-time test below is the episode (`test_unit: episode`; the "
            "seed-level tests further down are the exception): the training seeds replay the same "
            "episodes, and which episodes a policy wins repeats across its seeds, so the (seed, episode) pairs of one "
            "episode are not independent. Success: per episode d = a's successes summed over its seeds minus b's (a "
            "policy without seeds counts seeds x its success), the exact sign-flip test of d (rows marked †); two "
            "policies without seeds: exact McNemar test on the episodes. Navigation time: Wilcoxon signed-rank test "
            "over episodes, each episode's value the mean difference over the seeds both sides finished. "
            if by_episode
            else "Pairs are (training seed, episode). Success: exact McNemar test (two-sided binomial test on the "
            "discordant pairs; against a policy without seeds, the test marked † below); navigation time: Wilcoxon "
            "signed-rank test over episodes both sides finished (a policy without seeds pairs its episode with that "
            "episode of every seed). "
            if against_fixed
            else "Pairs are (training seed, episode); a policy without seeds pairs its episode with that episode of "
            "every seed. Success: exact McNemar test (two-sided binomial test on the discordant pairs); navigation "
            "time: Wilcoxon signed-rank test over episodes both sides finished. "
        )
        + f"Holm-Bonferroni correction within each endpoint: {fam.get('success', 0)} success tests and "
        f"{fam.get('navigation_time_s', 0)} navigation-time tests; significant = Holm-adjusted p <= {mc['alpha']}.",
        "",
        f"Minimum detectable difference (MDD): the difference in success rate the McNemar design detects with "
        f"{100 * summary['power']:.0f} % power at the observed discordant fraction (Connor's 1987 normal "
        f"approximation), at alpha = {mc['alpha']} and at the strictest Holm level alpha / {max(fam.get('success', 0), 1)}; "
        "'-' where no difference the observed discordance allows reaches that power (or no pair is discordant)"
        + ("; McNemar rows only." if by_episode else "."),
        "",
    ]
    if by_episode:
        lines += [
            "Rows marked †: the sign-flip test of d (H0: d symmetric about 0, i.e. swapping the two sides within an "
            "episode changes nothing), its mean / seeds the difference with a bootstrap percentile interval over "
            "episodes; n counts episodes and b10 / b01 do not apply.",
            "",
        ]
    elif against_fixed:
        lines += [
            "A policy with training seeds against one without (a deterministic planner, run once on the same "
            "episodes; rows marked †) counts each of the planner's episodes once: per episode d = the seeded "
            "policy's successes summed over its seeds minus seeds x the planner's success, the exact sign-flip test "
            "of d (H0: d symmetric about 0), its mean / seeds the difference with a bootstrap percentile interval "
            "over episodes; n counts episodes and b10 / b01 do not apply.",
            "",
        ]
    exact = any("difference_exact_ci" in t for t in summary["tests"])
    if exact:
        lines += [
            "The interval of a success difference is the exact conditional one (the Clopper-Pearson interval of the "
            "discordant pairs' split, mapped onto the difference): it excludes 0 exactly when p < 0.05"
            + (
                " (McNemar rows; a † row's bootstrap interval is not the inversion of its test, so near p = 0.05 the "
                "two can disagree)"
                if against_fixed
                else ""
            )
            + ". The verdict "
            f"reads the Holm-adjusted p at alpha = {mc['alpha']}, so a comparison whose interval excludes 0 can still "
            "show no difference once the family of tests is counted; 'no difference shown' is not a finding of "
            "equality.",
            "",
            "| split | a | b | n | b10 (a only) | b01 (b only) | success diff a-b [95 % CI] | p | p Holm | verdict "
            "| MDD | MDD Holm |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
    else:
        lines += [
            "| split | a | b | n | b10 (a only) | b01 (b only) | success diff a-b [95 % CI] | p | p Holm | MDD | MDD Holm |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]

    def side(s: Mapping[str, str]) -> str:
        return f"{s['policy']}/{s['arm']}"

    for t in summary["tests"]:
        if t["endpoint"] != "success":
            continue
        if t.get("missing"):
            empty = " | | | | | | |" + (" |" if exact else "")
            lines.append(f"| {t['split']} | {side(t['a'])} | {side(t['b'])} | missing |{empty}")
            continue
        fixed = "b01" not in t  # a seeded policy against a deterministic one (seeds_against_fixed)
        lo, hi = t["difference_exact_ci"] if exact and not fixed else t["difference_ci"]
        diff = f"{100 * t['difference']:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}]" if lo is not None else "-"
        diff += " †" if fixed else ""
        mdd = "-" if t.get("mdd") is None else f"{100 * t['mdd']:.1f}"
        mddh = "-" if t.get("mdd_holm_strictest") is None else f"{100 * t['mdd_holm_strictest']:.1f}"
        star = " *" if t.get("significant") else ""
        verdict = f" {t.get('verdict', '-')} |" if exact else ""
        lines.append(
            f"| {t['split']} | {side(t['a'])} | {side(t['b'])} | {t['n']} | {t.get('b10', '-')} | {t.get('b01', '-')} | "
            f"{diff} | "
            f"{_p(t['p_value'])} | {_p(t['p_holm'])}{star} |{verdict} {mdd} | {mddh} |"
        )
    seed_rows = [t for t in summary["tests"] if t["endpoint"] == "success" and t.get("seed_level")]
    if seed_rows:
        lines += [
            "",
            "Seed level (secondary): the "
            + ("episode-level tests above are" if by_episode else "McNemar test above is")
            + " conditional on the trained policies, so "
            + ("they do" if by_episode else "it does")
            + " not count the variance between training seeds. Here each training seed's success rate over the same paired "
            "episodes is one observation, paired by seed as declared: the paired t-test and 95 % t-interval on the "
            "per-seed differences (seed i of a against seed i of b; a policy without seeds is one fixed rate on the "
            "same episodes, which makes it a one-sample test), Holm-corrected over "
            f"the {fam.get('success_seed_level', 0)} seed-level tests. With {_count(len(summary['seeds']))} seeds "
            "per arm these intervals are wide: a difference can be clear episode by episode and still undetermined "
            "across training seeds.",
            "",
            "| split | a | b | per-seed rates a | per-seed rates b | diff a-b [95 % CI] | df | p | p Holm |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for t in seed_rows:
            sl = t["seed_level"]
            lo, hi = sl["difference_ci"]
            diff = f"{100 * sl['difference']:+.1f}" + (
                f" [{100 * lo:+.1f}, {100 * hi:+.1f}]" if lo is not None and hi is not None else ""
            )
            ra = " / ".join(f"{100 * r:.1f}" for r in sl["rates_a"])
            rb = " / ".join(f"{100 * r:.1f}" for r in sl["rates_b"])
            df = "-" if sl.get("df") is None else f"{sl['df']:.1f}"
            star = " *" if sl.get("significant") else ""
            lines.append(
                f"| {t['split']} | {side(t['a'])} | {side(t['b'])} | {ra} | {rb} | {diff} | {df} | "
                f"{_p(sl.get('p_value'))} | {_p(sl.get('p_holm'))}{star} |"
            )
    lines += [
        "",
        (
            "Navigation time (s), a - b, per episode the mean over the seeds both sides finished (episodes with at "
            "least one; median and mean over those episodes):"
            if by_episode
            else "Navigation time (s) of episodes both sides finished, a - b:"
        ),
        "",
        f"| split | a | b | {'episodes' if by_episode else 'pairs'} | median diff | mean diff | p | p Holm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for t in summary["tests"]:
        if t["endpoint"] != "navigation_time_s":
            continue
        med = "-" if t.get("median_difference") is None else f"{t['median_difference']:+.2f}"
        mean = "-" if t.get("mean_difference") is None else f"{t['mean_difference']:+.2f}"
        star = " *" if t.get("significant") else ""
        lines.append(
            f"| {t['split']} | {side(t['a'])} | {side(t['b'])} | {t['n']} | {med} | {mean} | {_p(t['p_value'])} | "
            f"{_p(t['p_holm'])}{star} |"
        )
    lines.append("")
    if figures:
        lines += ["## Plots", "", *[f"![{Path(f).stem}]({Path(f).name})" for f in figures], ""]
    lines += [f"Reproduce: `python -m agents.ablation {summary['config']}` (then `--summarize-only` to redraw).", ""]
    return "\n".join(lines)
