"""The dry run: every cell of a grid with its state (on disk, or done from committed results) and estimated time."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from agents.ablation.cells import (
    RATE_SOURCES,
    Cell,
    CellStatus,
    _hms,
    check_environments,
    estimate_seconds,
    measured_rates,
    recorded_rates,
)
from agents.ablation.config import CELL_STATES, AblationConfig, PolicySpec
from agents.ablation.results import plan
from crowdnav_mesrnn.config import ConfigError


def _from_results(statuses: Sequence[CellStatus]) -> str:
    """``"; done from committed results: 20 in results/ablation/planners, ..."`` ("" when no cell is)."""
    per: dict[str, int] = {}
    for st in statuses:
        if st.source:
            per[st.source] = per.get(st.source, 0) + 1
    return "; done from committed results: " + ", ".join(f"{n} in {f}" for f, n in per.items()) if per else ""


def dry_run(cfg: AblationConfig, cells: Sequence[Cell], workers: int, out: Callable[[str], None] = print) -> None:
    """Print every cell with its state and estimated time, and the totals."""
    statuses = plan(cfg, cells)
    rates, recorded = measured_rates(cfg), recorded_rates(cfg)

    def describe(p: PolicySpec) -> str:
        arms = f"arms {'/'.join(p.arms)}" if p.arms else "all arms"
        budget = f", {p.timesteps:,} steps x {p.n_envs} envs" if p.learned else ""
        return f"{p.name} ({p.kind}, {arms}{budget})"

    pol = "; ".join(describe(p) for p in cfg.policies)
    out(
        f"grid {cfg.name}: splits {', '.join(cfg.splits)}; arms {', '.join(cfg.arm_labels)}; "
        f"seeds {', '.join(map(str, cfg.seeds))}; policies {pol}; {cfg.episodes} evaluation episodes per cell"
    )
    if cfg.episodes_from != "test":
        out(f"evaluation episodes: {cfg.episodes_described()}")
    out(f"cells in {cfg.runs_path()}/, summaries in {cfg.out_path()}/")
    try:
        check_environments(cfg, [st.cell for st in statuses if st.state != "done"])
    except ConfigError as exc:  # the dry run lists the cells anyway; running them is refused (run_grid)
        out(f"WARNING: the grid would not run: {exc}")
    out(f"{'state':<8} {'estimate':>9}  {'from':<8} cell")
    total = 0.0
    counts = dict.fromkeys(CELL_STATES, 0)
    used: dict[str, dict[str, int]] = {s: {"train": 0, "eval": 0} for s in RATE_SOURCES}
    for st in statuses:
        counts[st.state] += 1
        secs, src = estimate_seconds(cfg, st.cell, rates, recorded)
        if st.state != "done":
            total += secs
            used[src][st.cell.kind] += 1
        est = "-" if st.state == "done" else _hms(secs)
        reason = f"  ({st.reason})" if st.reason else ""
        out(f"{st.state:<8} {est:>9}  {src if st.state != 'done' else '':<8} {st.cell.name}{reason}")
    n_train = sum(c.kind == "train" for c in cells)
    out(
        f"{len(cells)} cells ({n_train} train, {len(cells) - n_train} eval): "
        + ", ".join(f"{k} {v}" for k, v in counts.items())
        + _from_results(statuses)
    )
    where = {
        "runs": f"the throughput of finished cells in {cfg.runs_path()}/",
        "results": f"the finished cells recorded in {cfg.out_path() / 'cells.json'}",
        "config": f"the config's estimates (no finished cell of that kind, policy and forecast source; {cfg.source or 'config'})",
    }
    parts = [
        f"{n['train'] + n['eval']} cells ({n['train']} train, {n['eval']} eval) from {where[s]}"
        for s, n in used.items()
        if n["train"] + n["eval"]
    ]
    out("time estimates: " + ("; ".join(parts) if parts else "none (every cell is done)"))
    out(
        f"estimated compute left {_hms(total)}; with {workers} worker(s) at a time, wall time >= {_hms(total / workers)} "
        "(evaluations wait for their training runs)"
    )
