"""The CPU-time budget of a comparison plan: ``crowdnav-mesrnn predictor plan FILE --dry-run``.

Throughputs are measured once per distinct training configuration on zara1 training windows (cached in the plan's
``OUT/rates.json``) or read from the epochs of finished runs, and scaled to each split by its mean pedestrians per
window; :func:`dry_run` lists every run of a stage with its status and estimated CPU time.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crowdnav_mesrnn.studies.plan import Candidate, Plan, Run, run_dir, stage_runs, status
from crowdnav_mesrnn.utils import atomic_write_json


@dataclass(frozen=True)
class Rate:
    """Measured throughput of one training configuration (zara1 training windows)."""

    train_windows_per_s: float
    val_windows_per_s: float
    mean_pedestrians: float
    """Mean pedestrians per window (incl. context) of the batches measured; costs scale with it."""


def _cost_key(mcfg: Any, tcfg: Any) -> str:
    arch = mcfg.to_dict()
    train = {k: getattr(tcfg, k) for k in ("teacher_forcing", "precision", "batch_size", "augment_rotation")}
    return json.dumps({"model": arch, "train": train}, sort_keys=True)


def measure_rate(mcfg: Any, tcfg: Any, batches_count: int = 3, data_dir: str | None = None) -> Rate:
    """Time ``batches_count`` training steps (batches spread over the size range) and the validation
    rollout of the same windows, on zara1 training windows (one thread)."""
    import numpy as np
    import torch

    from crowdnav_mesrnn.data import MinMax, collate, split_windows
    from crowdnav_mesrnn.evaluation.metrics import batches, collect_forecasts
    from crowdnav_mesrnn.models.learned import LearnedPredictor
    from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
    from crowdnav_mesrnn.training.trainer import clip_gradients, make_optimizer, rotate_windows, training_loss

    windows = split_windows("zara1", "train", tcfg.min_scored, data_dir)
    norm = MinMax.fit(np.concatenate([w.positions[w.present] for w in windows]))
    # Batches as training makes them (bucketed by size); time ``batches_count`` of them spread evenly
    # over the size range, after the smallest as warm-up.
    chunks = list(batches(windows, tcfg.batch_size))
    picks = np.unique(np.linspace(0, len(chunks) - 1, batches_count).round().astype(int))
    chunks = [chunks[0], *(chunks[i] for i in picks)]
    torch.manual_seed(0)
    net = StructuralRNN(mcfg).train()
    opt = make_optimizer(net, tcfg)
    rng = np.random.default_rng(0)
    seen = peds = 0
    elapsed = 0.0
    for j, chunk in enumerate(chunks):
        t0 = time.perf_counter()
        pos, pres, _ = collate([windows[i] for i in chunk])
        if tcfg.augment_rotation:
            pos = rotate_windows(pos, pres, rng)
        p, m = torch.from_numpy(pos), torch.from_numpy(pres)
        p = torch.where(m.unsqueeze(-1), norm.normalise(p), torch.zeros_like(p))
        loss = training_loss(net, p, m, tcfg.teacher_forcing, tcfg.precision, tcfg.nll_beta, tcfg.mean_loss)
        opt.zero_grad()
        loss.backward()
        clip_gradients(net, tcfg.grad_clip)
        opt.step()
        if j:  # the first batch warms up
            elapsed += time.perf_counter() - t0
            seen += len(chunk)
            peds += sum(windows[i].num_peds for i in chunk)
    pred = LearnedPredictor(net.eval(), norm)
    val = [windows[i] for c in chunks[1:] for i in c]
    t0 = time.perf_counter()
    from crowdnav_mesrnn.evaluation.metrics import evaluate_windows

    evaluate_windows(pred.predict_batch, val, norm)
    if pred.has_distribution:  # validation also rolls out the distribution (its NLL)
        collect_forecasts(val, distribution=pred.predict_distribution_batch)
    val_rate = len(val) / (time.perf_counter() - t0)
    return Rate(seen / elapsed, val_rate, peds / seen)


def epoch_rates(out: Path) -> list[float]:
    """The training windows/s of every epoch trained in run folder ``out`` (``history`` of its
    ``last.pt``); empty when there is none or it cannot be read (the run itself says so when resumed)."""
    import torch

    last = out / "last.pt"
    if not last.is_file():
        return []
    try:
        history = torch.load(last, map_location="cpu", weights_only=True).get("history") or []
    except Exception:
        return []
    return [float(h["windows_per_s"]) for h in history if float(h.get("windows_per_s", 0.0)) > 0]


def observed_rates(
    plan: Plan, sizes: dict[str, dict[str, float]], configs: dict[tuple[str, str], Any]
) -> dict[tuple[str, str], tuple[float, int]]:
    """Per (model, candidate): the training rate of the epochs already trained in this plan's run folders
    (the ``windows_per_s`` of each epoch in ``last.pt``), converted to zara1-sized windows like the
    measurement, and the number of epochs it comes from. Total windows over total seconds, so long epochs
    weigh as much as they cost."""
    windows: dict[tuple[str, str], float] = {}
    seconds: dict[tuple[str, str], float] = {}
    epochs: dict[tuple[str, str], int] = {}
    for m in plan.models:
        for c in plan.candidates:
            ref_peds = configs[(m, c.name)][2].mean_pedestrians
            for s in plan.splits:
                for k in plan.seeds:
                    n = sizes[s]["train"]
                    for rate in epoch_rates(run_dir(plan, m, s, c.name, k)):
                        # n windows of this split cost n / rate s; as zara1-sized windows: n * peds / ref
                        equiv = n * sizes[s]["train_peds"] / ref_peds
                        key = (m, c.name)
                        windows[key] = windows.get(key, 0.0) + equiv
                        seconds[key] = seconds.get(key, 0.0) + n / rate
                        epochs[key] = epochs.get(key, 0) + 1
    return {key: (windows[key] / seconds[key], epochs[key]) for key in windows}


def _split_sizes(splits: Iterable[str], min_scored: int, data_dir: str | None) -> dict[str, dict[str, float]]:
    import numpy as np

    from crowdnav_mesrnn.data import split_windows

    out = {}
    for s in splits:
        train = split_windows(s, "train", min_scored, data_dir)
        val = split_windows(s, "val", 2, data_dir)
        out[s] = {
            "train": len(train),
            "val": len(val),
            "train_peds": float(np.mean([w.num_peds for w in train])),
            "val_peds": float(np.mean([w.num_peds for w in val])),
        }
    return out


def dry_run(
    plan: Plan,
    stage: str = "all",
    measure_batches: int = 3,
    remeasure: bool = False,
    data_dir: str | None = None,
    cores: int = 2,
) -> str:
    """Every run of ``stage`` with its status and estimated CPU time, and the totals.

    Throughputs are measured once per distinct configuration on zara1 training windows (cached in
    ``OUT/rates.json``; ``remeasure`` refreshes them) and scaled to each split by its mean pedestrians
    per window. Seed runs whose candidate is not selected yet are costed with the most expensive
    candidate (an upper bound).
    """
    import torch

    from crowdnav_mesrnn.training.trainer import load_configs

    torch.set_num_threads(1)
    cache_path = plan.out_dir / "rates.json"
    cache: dict[str, Any] = json.loads(cache_path.read_text()) if cache_path.is_file() and not remeasure else {}
    sizes = _split_sizes(plan.splits, 2, data_dir)
    configs: dict[tuple[str, str], Any] = {}
    measured_now = 0
    for m in plan.models:
        for c in plan.candidates:
            mcfg, tcfg = load_configs(m, c.config_path(m), {**c.overrides, "split": "zara1"})
            key = _cost_key(mcfg, tcfg)
            if key not in cache:
                r = measure_rate(mcfg, tcfg, measure_batches, data_dir)
                cache[key] = r.__dict__
                measured_now += 1
            configs[(m, c.name)] = (mcfg, tcfg, Rate(**cache[key]))
    if measured_now:
        atomic_write_json(cache_path, cache)

    observed = observed_rates(plan, sizes, configs)

    def cpu_s(run: Run, candidate: Candidate) -> float:
        _, tcfg, rate = configs[(run.model, candidate.name)]
        sz = sizes[run.split]
        obs = observed.get((run.model, candidate.name))
        train_zara1 = obs[0] if obs else rate.train_windows_per_s
        train_rate = train_zara1 * rate.mean_pedestrians / sz["train_peds"]
        val_rate = rate.val_windows_per_s * rate.mean_pedestrians / sz["val_peds"]
        state, ep = status(run)
        left = 0 if state == "done" else tcfg.epochs - ep
        return left * (sz["train"] / train_rate + sz["val"] / val_rate)

    lines = [
        f"plan {plan.source}: {len(plan.models)} models x {len(plan.splits)} splits x {len(plan.candidates)} "
        f"candidates, then seeds {list(plan.seeds)} of the selected candidate -> {plan.out_dir}",
        "",
        "measured throughput, 1 thread, zara1 training windows (windows/s; cached in "
        f"{cache_path}{', measured now' if measured_now else ''}):",
    ]
    for (m, cname), (_, tcfg, rate) in configs.items():
        obs = observed.get((m, cname))
        seen = f"; trained so far: {obs[0]:.1f} over {obs[1]} epoch(s), used instead" if obs else ""
        lines.append(
            f"  {m:<7}{cname:<20}train {rate.train_windows_per_s:6.1f}  val {rate.val_windows_per_s:7.1f}  "
            f"({rate.mean_pedestrians:.1f} pedestrians/window; {tcfg.epochs} epochs, "
            f"{'teacher forcing' if tcfg.teacher_forcing else 'own rollout'}, {tcfg.precision}{seen})"
        )
    lines += [
        "",
        f"{'stage':<11}{'model':<8}{'split':<7}{'candidate':<20}{'seed':>5}{'status':>14}{'CPU min':>9}  command",
    ]
    totals: dict[str, float] = {}  # minutes; seeds not yet selected costed as the dearest candidate
    spread: dict[str, float] = {}  # minutes saved if every waiting seed uses the cheapest candidate
    count: dict[str, int] = {}
    stages = ("candidates", "seeds") if stage == "all" else (stage,)
    for st in stages:
        runs, waiting = stage_runs(plan, st)
        for run in runs:
            state, ep = status(run)
            minutes = cpu_s(run, run.candidate) / 60
            totals[st] = totals.get(st, 0.0) + minutes
            count[st] = count.get(st, 0) + 1
            label = state if state != "partial" else f"epoch {ep}"
            lines.append(
                f"{st:<11}{run.model:<8}{run.split:<7}{run.candidate.name:<20}{run.seed:>5}{label:>14}"
                f"{minutes:>9.1f}  {run.command()}"
            )
        for m, s in waiting:
            costs = {c.name: cpu_s(Run(st, m, s, c, 0, Path("/nonexistent")), c) / 60 for c in plan.candidates}
            cheap, dear = min(costs, key=costs.get), max(costs, key=costs.get)
            for k in plan.seeds:
                if k == plan.selection_seed:
                    continue
                totals[st] = totals.get(st, 0.0) + costs[dear]
                spread[st] = spread.get(st, 0.0) + costs[dear] - costs[cheap]
                count[st] = count.get(st, 0) + 1
                lines.append(
                    f"{st:<11}{m:<8}{s:<7}{'(to be selected)':<20}{k:>5}{'waits':>14}{costs[dear]:>9.1f}  "
                    f"(upper bound, as {dear}; as {cheap}: {costs[cheap]:.1f} min)"
                )
    grand = sum(totals.values())
    saved = sum(spread.values())
    lines.append("")
    for st, minutes in totals.items():
        span = f"{(minutes - spread[st]) / 60:.1f}-" if spread.get(st) else ""
        lines.append(f"{st}: {count[st]} runs, {span}{minutes / 60:.1f} CPU-hours left")
    lo_total = (grand - saved) / 60
    lines.append(
        f"total: {lo_total:.1f}-{grand / 60:.1f} CPU-hours left (the range is the candidate the seeds will use) = "
        f"about {lo_total / cores:.1f}-{grand / 60 / cores:.1f} h on {cores} cores "
        f"(shards --shard 0/{cores} ... --shard {cores - 1}/{cores}, one thread each)"
    )
    lines.append(
        "estimates scale the zara1 rate by each split's mean pedestrians per window; the training rate is the one "
        "of the epochs this plan has already trained with that configuration where there are any (the short "
        "measurement over-weights the largest windows), else the measurement; both on whatever else was "
        "running on this machine"
    )
    return "\n".join(lines)
