"""The predictor comparison as one resumable plan: candidates x models x splits, then seeds.

A plan file (``configs/predictor/candidates.yaml``) declares the candidate configurations once; every
candidate is applied to every model. Stages:

- ``candidates``: every (model, split, candidate) trained with ``selection_seed``;
- ``seeds``: per (model, split), the candidate with the lowest validation ADE (validation data only)
  trained with every other seed of ``seeds``;
- ``export`` (explicit only): per (model, split), the seed with the lowest validation ADE becomes the
  shipped pretrained weights.

A plan with ``select_on: nll`` (distribution heads) selects on the validation negative log-likelihood instead
of the ADE, at every one of those places (and its runs keep the epoch of lowest validation NLL).

Each run is a folder ``OUT/MODEL/SPLIT/CANDIDATE/seedK`` holding what ``predictor train`` writes plus
``done.json`` once finished; finished runs are skipped and interrupted ones resumed, so the same
command can be re-run (or run as shards ``--shard i/n`` on several cores) until everything is done. A run
being trained holds a lock on its folder, so two processes never train the same run (one skips it).
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from crowdnav_mesrnn.config import ConfigError, check_keys, load_yaml
from crowdnav_mesrnn.data.constants import SPLITS, check_split
from crowdnav_mesrnn.models.base import LEARNED_MODELS
from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text, code_version, file_lock

STAGES = ("candidates", "seeds", "all", "export")
REPO_ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Candidate:
    """One candidate configuration, applied to every model."""

    name: str
    """Label of the candidate (a folder name)."""
    config: str
    """YAML path with ``{model}`` (relative paths: the working directory, else the repository root)."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """Model or train keys set on top of the YAML (``set:`` in the plan file)."""

    def config_path(self, model: str) -> Path:
        path = Path(self.config.format(model=model))
        if path.is_absolute() or path.exists():
            return path
        return REPO_ROOT / path


@dataclass(frozen=True)
class Plan:
    """A parsed plan file."""

    models: tuple[str, ...]
    splits: tuple[str, ...]
    candidates: tuple[Candidate, ...]
    selection_seed: int = 0
    seeds: tuple[int, ...] = (0, 1, 2)
    out_dir: Path = Path("runs/predictor/plan")
    source: str = ""
    """The plan file (for messages and reproduce commands)."""
    export: bool = True
    """Whether stage ``export`` may ship this plan's weights (``export: false`` for a plan that only
    measures, e.g. a fixed-candidate comparison that reuses another plan's runs)."""
    select_on: str = "ade"
    """The validation figure that selects candidates, seeds to ship and each run's best epoch: ``ade`` or
    ``nll`` (distribution heads only)."""

    @property
    def done_key(self) -> str:
        """The ``done.json`` field selection reads."""
        return "best_val_nll_m" if self.select_on == "nll" else "best_val_ade_m"

    @property
    def unit(self) -> str:
        return "NLL" if self.select_on == "nll" else "ADE"


@dataclass(frozen=True)
class Run:
    """One training run of the plan."""

    stage: str
    model: str
    split: str
    candidate: Candidate
    seed: int
    out: Path

    select_on: str = "ade"

    @property
    def overrides(self) -> dict[str, Any]:
        extra = {"select_on": self.select_on} if self.select_on != "ade" else {}
        return {**self.candidate.overrides, **extra, "seed": self.seed, "split": self.split}

    def command(self) -> str:
        """The equivalent single ``predictor train`` command."""
        extra = {"select_on": self.select_on} if self.select_on != "ade" else {}
        sets = " ".join(
            f"--set {k}={yaml_scalar(v)}" for k, v in {**self.candidate.overrides, **extra, "seed": self.seed}.items()
        )
        config = self.candidate.config.format(model=self.model)
        return (
            f"crowdnav-mesrnn predictor train --model {self.model} --split {self.split} --config {config} "
            f"{sets} --out {self.out}"
        )


def yaml_scalar(value: Any) -> str:
    """``value`` as it would be written after ``--set KEY=`` (``true``, ``0.5``, ``[1, 2]``)."""
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()


def load_plan(path: str | os.PathLike[str]) -> Plan:
    """Read and check a plan file; unknown keys, models, splits or missing configs are errors."""
    path = Path(path)
    raw = load_yaml(path)
    check_keys(
        raw, ["models", "splits", "candidates", "selection_seed", "seeds", "out_dir", "export", "select_on"], path.name
    )
    select_on = raw.get("select_on", "ade")
    if select_on not in ("ade", "nll"):
        raise ConfigError(f"{path}: 'select_on' is {select_on!r}; valid: ade, nll")
    ships = raw.get("export", True)
    if not isinstance(ships, bool):
        raise ConfigError(f"{path}: 'export' is {ships!r}; valid: true or false")
    models = tuple(raw.get("models") or LEARNED_MODELS)
    for m in models:
        if m not in LEARNED_MODELS:
            raise ConfigError(f"{path}: unknown model {m!r}; valid: {', '.join(LEARNED_MODELS)}")
    splits = tuple(raw.get("splits") or SPLITS)
    for s in splits:
        check_split(s)
    cands_raw = raw.get("candidates")
    if not isinstance(cands_raw, dict) or not cands_raw:
        raise ConfigError(f"{path}: 'candidates' must map candidate names to {{config, set}}")
    candidates = []
    for name, spec in cands_raw.items():
        spec = spec or {}
        check_keys(spec, ["config", "set"], f"{path.name} candidate {name!r}")
        if "config" not in spec:
            raise ConfigError(f"{path}: candidate {name!r} needs a 'config' path (may contain {{model}})")
        cand = Candidate(str(name), str(spec["config"]), dict(spec.get("set") or {}))
        for key in ("seed", "split", "select_on"):
            if key in cand.overrides:
                raise ConfigError(f"{path}: candidate {name!r} may not set {key!r} (the plan sets it)")
        for m in models:
            if not cand.config_path(m).is_file():
                raise ConfigError(f"{path}: candidate {name!r}: no config {cand.config_path(m)} for model {m!r}")
        candidates.append(cand)
    seeds = tuple(int(s) for s in raw.get("seeds", (0, 1, 2)))
    selection_seed = int(raw.get("selection_seed", 0))
    if selection_seed not in seeds:
        raise ConfigError(f"{path}: selection_seed {selection_seed} must be one of seeds {list(seeds)}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"{path}: seeds {list(seeds)} repeat a value")
    return Plan(
        models,
        splits,
        tuple(candidates),
        selection_seed,
        seeds,
        Path(raw.get("out_dir", "runs/predictor/plan")),
        str(path),
        ships,
        select_on,
    )


def run_dir(plan: Plan, model: str, split: str, candidate: str, seed: int) -> Path:
    return plan.out_dir / model / split / candidate / f"seed{seed}"


def candidate_runs(plan: Plan) -> list[Run]:
    """Every candidate for every model and split, with the selection seed."""
    return [
        Run(
            "candidates", m, s, c, plan.selection_seed, run_dir(plan, m, s, c.name, plan.selection_seed), plan.select_on
        )
        for m in plan.models
        for s in plan.splits
        for c in plan.candidates
    ]


def seed_runs(plan: Plan, model: str, split: str, candidate: Candidate) -> list[Run]:
    """The further seeds of the selected ``candidate`` (the selection-seed run is reused)."""
    return [
        Run("seeds", model, split, candidate, k, run_dir(plan, model, split, candidate.name, k), plan.select_on)
        for k in plan.seeds
        if k != plan.selection_seed
    ]


# ------------------------------------------------------------------ status and selection
def read_done(out: Path) -> dict[str, Any] | None:
    """The ``done.json`` of a finished run, else ``None``."""
    path = out / "done.json"
    return json.loads(path.read_text()) if path.is_file() else None


def status(run: Run) -> tuple[str, int]:
    """``("done" | "partial" | "todo", epochs finished)``."""
    done = read_done(run.out)
    if done is not None:
        return "done", int(done["epochs"])
    last = run.out / "last.pt"
    if last.is_file():
        import torch

        return "partial", int(torch.load(last, map_location="cpu", weights_only=True)["epoch"])
    return "todo", 0


def selected_candidate(plan: Plan, model: str, split: str) -> tuple[Candidate | None, dict[str, float]]:
    """The candidate with the lowest validation ADE (NLL with ``select_on: nll``) once all candidates of
    (model, split) are done (``None`` before), and every finished candidate's best validation figure."""
    vals: dict[str, float] = {}
    for c in plan.candidates:
        done = read_done(run_dir(plan, model, split, c.name, plan.selection_seed))
        if done is not None:
            vals[c.name] = float(done[plan.done_key])
    if len(vals) < len(plan.candidates):
        return None, vals
    best = min(plan.candidates, key=lambda c: (vals[c.name], c.name))
    return best, vals


def summary(plan: Plan) -> dict[str, dict[str, Any]]:
    """Per ``"model/split"``: candidates' validation ADE, the selected candidate, each finished seed's
    validation ADE and checkpoint, and the seed to ship (lowest validation ADE, once all seeds are done)."""
    out: dict[str, dict[str, Any]] = {}
    for m in plan.models:
        for s in plan.splits:
            cand, vals = selected_candidate(plan, m, s)
            row: dict[str, Any] = {
                f"candidates_{plan.done_key.removeprefix('best_')}": vals,
                "selected": cand.name if cand else None,
                "seeds": {},
            }
            if cand is not None:
                for k in plan.seeds:
                    folder = run_dir(plan, m, s, cand.name, k)
                    done = read_done(folder)
                    if done is not None:
                        row["seeds"][k] = {
                            "val_ade_m": float(done["best_val_ade_m"]),
                            "checkpoint": str(folder / "best.pt"),
                        }
                        if "best_val_nll_m" in done:
                            row["seeds"][k]["val_nll_m"] = float(done["best_val_nll_m"])
                if len(row["seeds"]) == len(plan.seeds):
                    field_ = "val_nll_m" if plan.select_on == "nll" else "val_ade_m"
                    row["shipped_seed"] = min(row["seeds"], key=lambda k: (row["seeds"][k][field_], k))
            out[f"{m}/{s}"] = row
    return out


# ------------------------------------------------------------------ executing
def _grid_index(plan: Plan, run: Run) -> int:
    """Position of ``run`` in its stage's full grid, whatever has been selected so far: candidates by
    (model, split, candidate), seeds by (model, split, seed). Stable while the seeds stage grows."""
    m, s = plan.models.index(run.model), plan.splits.index(run.split)
    if run.stage == "candidates":
        inner, k = len(plan.candidates), [c.name for c in plan.candidates].index(run.candidate.name)
    else:
        inner, k = len(plan.seeds), plan.seeds.index(run.seed)
    return (m * len(plan.splits) + s) * inner + k


def shard_filter(runs: list[Run], shard: tuple[int, int], plan: Plan) -> list[Run]:
    """The runs of ``shard = (i, n)``: those at positions ``i, i+n, i+2n, ...`` of the stage's full grid
    of ``plan`` (so a run keeps its shard while other (model, split) pairs become selected and the seeds
    stage grows)."""
    i, n = shard
    if not (n >= 1 and 0 <= i < n):
        raise ValueError(f"shard must be i/n with 0 <= i < n, got {i}/{n}")
    return [r for r in runs if _grid_index(plan, r) % n == i]


@contextlib.contextmanager
def run_lock(out: Path) -> Iterator[bool]:
    """An exclusive, non-blocking lock on a run folder (``OUT/.plan.lock``): yields False when another
    process holds it (that process is training the run). Released when the holder exits, even if killed;
    a no-op (always True) where file locks are unavailable."""
    out.mkdir(parents=True, exist_ok=True)
    with file_lock(out / ".plan.lock", blocking=False) as held:
        yield held


def parse_shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError as exc:
        raise ValueError(f"--shard expects i/n (e.g. 0/2), got {text!r}") from exc
    return i, n


def train_run(
    run: Run, data_dir: str | None = None, progress: bool = False, log: Callable[[str], None] = print
) -> dict:
    """Train (or resume) one run and write ``done.json``; returns its content."""
    from crowdnav_mesrnn.training.trainer import Trainer, load_configs

    overrides = dict(run.overrides)
    if data_dir:
        overrides["data_dir"] = data_dir
    mcfg, tcfg = load_configs(run.model, run.candidate.config_path(run.model), overrides)
    trainer = Trainer(mcfg, tcfg, run.out)
    if (run.out / "last.pt").is_file():
        trainer.resume()
        log(f"resumed {run.out} at epoch {trainer.epoch}")
    run.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        run.out / "run.yaml",
        yaml.safe_dump(
            {"command": run.command(), "plan": run.stage, "model": mcfg.to_dict(), "train": tcfg.__dict__},
            sort_keys=False,
        ),
    )
    t0 = time.process_time()
    res = trainer.fit(progress=progress, log=log)
    done = {
        "model": run.model,
        "split": run.split,
        "candidate": run.candidate.name,
        "seed": run.seed,
        "epochs": trainer.epoch,
        "best_val_ade_m": res["best_val_ade_m"],
        **({"best_val_nll_m": res["best_val_nll_m"]} if "best_val_nll_m" in res else {}),
        "select_on": res["select_on"],
        "cpu_seconds_this_session": time.process_time() - t0,
        "code_version": code_version(),
        "command": run.command(),
    }
    atomic_write_json(run.out / "done.json", done)
    return done


def stage_runs(plan: Plan, stage: str) -> tuple[list[Run], list[tuple[str, str]]]:
    """Runs of ``stage`` (``candidates``/``seeds``/``all``) that can be known now, and the (model, split)
    pairs whose seed runs wait for their candidates."""
    runs: list[Run] = []
    waiting: list[tuple[str, str]] = []
    if stage in ("candidates", "all"):
        runs += candidate_runs(plan)
    if stage in ("seeds", "all"):
        for m in plan.models:
            for s in plan.splits:
                cand, _ = selected_candidate(plan, m, s)
                if cand is None:
                    waiting.append((m, s))
                else:
                    runs += seed_runs(plan, m, s, cand)
    return runs, waiting


def execute(
    plan: Plan,
    stage: str = "all",
    shard: tuple[int, int] = (0, 1),
    data_dir: str | None = None,
    log: Callable[[str], None] = print,
) -> int:
    """Run every unfinished run of ``stage`` in this shard; returns the number of runs still missing."""
    if stage == "export":
        return export(plan, log)
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; valid: {', '.join(STAGES)}")
    from crowdnav_mesrnn.training.trainer import keep_freed_memory

    keep_freed_memory()
    stages = ("candidates", "seeds") if stage == "all" else (stage,)
    for st in stages:
        runs, _ = stage_runs(plan, st)
        for run in shard_filter(runs, shard, plan):
            if status(run)[0] == "done":
                continue
            with run_lock(run.out) as mine:
                if not mine:
                    log(
                        f"[{st}] {run.model} {run.split} {run.candidate.name} seed {run.seed}: another process is training it"
                    )
                    continue
                if status(run)[0] == "done":  # finished while we waited for the lock
                    continue
                log(f"[{st}] {run.model} {run.split} {run.candidate.name} seed {run.seed} -> {run.out}")
                done = train_run(run, data_dir, log=log)
                if plan.select_on == "nll":
                    log(f"  done: best val NLL {done['best_val_nll_m']:.3f} (ADE {done['best_val_ade_m']:.3f} m)")
                else:
                    log(f"  done: best val ADE {done['best_val_ade_m']:.3f} m")
    runs, waiting = stage_runs(plan, stage)
    missing = sum(status(r)[0] != "done" for r in runs) + len(waiting) * (len(plan.seeds) - 1)
    if missing:
        log(
            f"{missing} run(s) of stage {stage!r} not finished (other shards, or seeds waiting for candidates: "
            f"{', '.join(f'{m}/{s}' for m, s in waiting) or 'none'}); re-run this command when they are."
        )
    return missing


def export(plan: Plan, log: Callable[[str], None] = print) -> int:
    """Ship, per (model, split) with every seed finished, the seed with the lowest validation ADE."""
    from crowdnav_mesrnn.models.pretrained import export_checkpoint

    if not plan.export:
        raise ConfigError(
            f"{plan.source}: 'export' is false, so this plan never ships weights; export the plan that selected "
            "the shipped configuration instead"
        )
    missing = 0
    for key, row in summary(plan).items():
        model, split = key.split("/")
        if "shipped_seed" not in row:
            missing += 1
            log(f"{key}: not all seeds finished; not exported")
            continue
        k = row["shipped_seed"]
        field_, unit = ("val_nll_m", "") if plan.select_on == "nll" else ("val_ade_m", " m")
        seeds = "; ".join(f"seed {s} {v[field_]:.3f}{unit}" for s, v in sorted(row["seeds"].items()))
        cands = "; ".join(f"{c} {v:.3f}{unit}" for c, v in sorted(row[f"candidates_{field_}"].items()))
        note = (
            f"lowest val {plan.unit} {row['seeds'][k][field_]:.3f}{unit} (seed {k}) of: {seeds}; candidate "
            f"{row['selected']} selected on val {plan.unit} (seed {plan.selection_seed}) among: {cands}; "
            f"plan {plan.source}"
        )
        path = export_checkpoint(row["seeds"][k]["checkpoint"], model, split, note)
        log(f"{key}: wrote {path}")
    return missing


# ------------------------------------------------------------------ budget
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


def main_plan(args: Any) -> int:
    """``crowdnav-mesrnn predictor plan`` (see :func:`crowdnav_mesrnn.cli_predictor.add_parser`)."""
    import torch

    torch.set_num_threads(args.threads)
    plan = load_plan(args.file)
    if args.dry_run:
        print(
            dry_run(
                plan,
                args.stage if args.stage != "export" else "all",
                args.measure_batches,
                args.remeasure,
                args.data_dir,
            )
        )
        return 0
    execute(plan, args.stage, parse_shard(args.shard), args.data_dir, log=lambda s: print(s, flush=True))
    return 0
