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
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, check_keys, load_yaml
from crowdnav_mesrnn.data.constants import SPLITS, check_split
from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text, code_version, file_lock

#: The shipped structural RNNs (weights per split), as the registry lists them.
LEARNED_MODELS: tuple[str, ...] = predictors.names(predictors.PRETRAINED, plugins=False)

STAGES = ("candidates", "seeds", "all", "export")
REPO_ROOT = Path(__file__).resolve().parents[2]


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
