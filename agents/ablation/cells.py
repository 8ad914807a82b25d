"""Cells (one training run or one evaluation), their specs, folders and states; throughput estimates and the dry run."""

from __future__ import annotations

import dataclasses
import fnmatch
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from agents.ablation.config import (
    CELL_JSON,
    DONE,
    LEARNED_SOURCES,
    TRAIN_RUN,
    AblationConfig,
    Arm,
    PolicySpec,
)
from agents.evaluation import episode_part
from crowdnav_mesrnn.config import ConfigError, load_yaml
from crowdnav_mesrnn.data.constants import SPLITS


@dataclass(frozen=True)
class Cell:
    """One unit of work: a training run or an evaluation."""

    kind: str
    """``train`` or ``eval``."""
    split: str
    policy: PolicySpec
    arm: Arm
    seed: int | None
    """Training seed (``None`` for non-learned policies)."""

    @property
    def name(self) -> str:
        base = f"{self.kind}/{self.split}/{self.policy.name}/{self.arm.label}"
        return base if self.seed is None else f"{base}/seed{self.seed}"

    @property
    def needs(self) -> str | None:
        """The training cell an evaluation cell evaluates (``None`` for planners and training cells)."""
        if self.kind == "eval" and self.policy.learned:
            return dataclasses.replace(self, kind="train").name
        return None

    @property
    def cpus(self) -> int:
        """CPUs the cell keeps busy."""
        return self.policy.cpus if self.kind == "train" else 1


def expand(cfg: AblationConfig) -> list[Cell]:
    """Every cell of the grid: training cells first, then evaluation cells, each in the order they run: by the
    policies' ``priority`` (lower first), then split (in ``splits`` order), policy (config order), arm, seed. Without
    priorities that is the split, policy, arm, seed order."""
    train: list[Cell] = []
    evals: list[Cell] = []
    for split in cfg.splits:
        for policy in cfg.policies:
            for arm in (a for a in cfg.arms if policy.uses(a)):
                if policy.learned:
                    for seed in cfg.seeds:
                        train.append(Cell("train", split, policy, arm, seed))
                        evals.append(Cell("eval", split, policy, arm, seed))
                else:
                    evals.append(Cell("eval", split, policy, arm, None))
    # stable: within a priority and split the order above (policy, arm, seed) stays
    return sorted(train, key=_run_order(cfg)) + sorted(evals, key=_run_order(cfg))


def _run_order(cfg: AblationConfig) -> Callable[[Cell], tuple[int, int]]:
    return lambda cell: (cell.policy.priority, cfg.splits.index(cell.split))


def check_environments(cfg: AblationConfig, cells: Iterable[Cell]) -> None:
    """Check the environment settings of every distinct evaluation environment of the planner cells ``cells`` with
    the environment's own config check (``envs.config.config_from``: unknown keys listed with the valid ones, values
    checked), as the cells would make them, so that a grid whose settings the environment refuses fails before any
    cell starts. Raises :class:`ConfigError` naming ``policies.<name>.env`` (or ``env``) and the arm."""
    from envs.config import config_from

    seen: set[str] = set()
    for cell in cells:
        if cell.kind != "eval" or cell.policy.learned:
            continue
        env = {**cfg.env_for(cell.policy), **cell.arm.env_overrides()}
        env.update(predictor=cell.arm.predictor, split=cell.split, **episode_part(cfg.episodes_from))
        key = json.dumps(env, sort_keys=True, default=str)
        if key in seen:
            continue
        seen.add(key)
        try:
            config_from(env, {})
        except ConfigError as exc:
            where = f"policies.{cell.policy.name}.env" if cell.policy.env else "env"
            raise ConfigError(
                f"ablation config key {where!r} (cell {cell.name}): the environment refuses these settings: {exc}"
            ) from None


def _canonical_yaml_sha256(path: str, timesteps: int | None = None) -> str | None:
    """sha256 of an agent YAML's parsed content (comments and layout do not count) as a training cell reads it; None if
    missing.

    A cell's budget is the grid's ``timesteps`` (:func:`agents.ablation.config.training_overrides`), never the YAML's
    ``n_timesteps``, so every entry's ``n_timesteps`` is hashed as ``float(timesteps)``: a budget written into an agent
    YAML (e.g. made whole rollouts, ``100352``) does not make the cells that never read it stale, and the form is the
    one the shipped YAMLs wrote before (``!!float 1e5``), so the committed grids' recorded specs stay the same."""
    try:
        content = load_yaml(path)
    except FileNotFoundError:
        return None
    if timesteps is not None:
        for key, entry in list(content.items()):
            if isinstance(entry, dict) and "n_timesteps" in entry:  # a new mapping: YAML aliases share one
                content[key] = {**entry, "n_timesteps": float(timesteps)}
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()


def cell_spec(cfg: AblationConfig, cell: Cell) -> dict[str, Any]:
    """Everything that defines a cell's result; a finished cell whose recorded spec differs is stale."""
    spec: dict[str, Any] = {
        "kind": cell.kind,
        "split": cell.split,
        "policy": cell.policy.name,
        "policy_kind": cell.policy.kind,
        "arm": cell.arm.label,
        "predictor": cell.arm.predictor,
        "noisy_oracle_ade_m": cell.arm.noisy_oracle_ade_m,
        "seed": cell.seed,
        "env": dict(sorted(cfg.env_for(cell.policy).items())),
        "env_revision": _env_revision(),
    }
    reaction = spec["env"].get("reaction")
    if reaction is not None:  # a model past its first revision (results of the others' first revisions stay done)
        from envs.reaction import revision_rules

        spec.update(revision_rules(reaction))
    spec.update(cell.arm.spec())  # only for a variant: the specs of every other arm stay as they were (cells stay done)
    if cell.kind == "train":
        spec.update(
            agent_config=cell.policy.config,
            agent_config_sha256=_canonical_yaml_sha256(cell.policy.config or "", cell.policy.timesteps),
            timesteps=cell.policy.timesteps,
            n_envs=cell.policy.n_envs,
            overrides=dict(cell.policy.overrides),
        )
    else:
        spec.update(episodes=cfg.episodes, eval_seed=cfg.eval_seed)
        if cfg.episodes_from != "test":  # only off the default: the specs of every grid before it stay as they were
            spec["episodes_from"] = cfg.episodes_from
        if cell.policy.learned:
            spec["model"] = cell.policy.model
        elif cell.policy.options:
            spec["options"] = dict(sorted(cell.policy.options.items()))
    return json.loads(json.dumps(spec, default=str))


def _env_revision() -> int:
    """The environment's rules (:data:`envs.crowd_nav.ENV_REVISION`): a cell finished under other rules (e.g.
    before the pop-in rule) is stale, so one table never mixes environment versions."""
    from envs.crowd_nav import ENV_REVISION

    return int(ENV_REVISION)


_WEIGHTS_CACHE: dict[tuple[str, str, float, int], str] = {}


def _file_sha256(path: Path) -> str:
    st = path.stat()
    key = (path.name, str(path), st.st_mtime, st.st_size)
    if key not in _WEIGHTS_CACHE:
        digest = hashlib.sha256()
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                digest.update(chunk)
        _WEIGHTS_CACHE[key] = digest.hexdigest()
    return _WEIGHTS_CACHE[key]


def weights_fingerprint(predictor: str) -> dict[str, str]:
    """sha256 of every shipped weights file an arm with this source uses (empty for sources without weights; for a
    predictor plug-in, its forecast-cache key per split: identity and weights).

    A split's cells use the weights of all five splits: its held-out scene is forecast by its own
    split's predictor, each training scene by the predictor of the split holding that scene out.
    A missing file is recorded as ``"missing"``.
    """
    from crowdnav_mesrnn import predictors

    if predictors.is_plugin(predictor):  # a plug-in: the forecast cache's key of the predictor each split loads
        from crowdnav_mesrnn.predictors import load
        from envs.forecasting.cache import predictor_fingerprint

        return {f"{predictor}@{s}": predictor_fingerprint(load(predictor, s)) or "unhashable" for s in SPLITS}
    if predictor not in LEARNED_SOURCES:
        return {}
    from crowdnav_mesrnn.models.pretrained import pretrained_path

    out: dict[str, str] = {}
    for split in SPLITS:
        path = pretrained_path(predictor, split)
        out[path.name] = _file_sha256(path) if path.is_file() else "missing"
    return out


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
        return data if isinstance(data, dict) else None
    except (OSError, ValueError):
        return None


def cell_dir(cfg: AblationConfig, cell: Cell | str) -> Path:
    return cfg.runs_path() / (cell if isinstance(cell, str) else cell.name)


def trained_model(train_dir: Path, which: str) -> Path | None:
    """The ``best``/``final`` model of a finished training cell folder (``None`` if absent): its policy file of the
    project's format, which loads without unpickling (:func:`agents.runs.run_model`), else the SB3 zip of a run
    trained before that format (whose evaluation then refuses to unpickle it and says how to convert it)."""
    from agents.runs import run_model

    meta = _read_json(train_dir / CELL_JSON) or {}
    return run_model(train_dir / meta.get("run_dir", TRAIN_RUN), which)


@dataclass
class CellStatus:
    cell: Cell
    state: str
    reason: str = ""
    meta: dict[str, Any] | None = None
    """The cell's ``cell.json`` (``None`` without a run folder)."""
    source: str = ""
    """For a cell without a run folder that is done from committed results: the results folder it is read from (the
    grid's ``out_dir`` or one of its ``reuse`` folders, as the config names it); ``""`` otherwise."""
    record: dict[str, Any] | None = None
    """The cell's record in :attr:`source`'s ``cells.json`` (``None`` unless :attr:`source`)."""


def cell_status(cfg: AblationConfig, cell: Cell, train_states: Mapping[str, CellStatus] | None = None) -> CellStatus:
    """The state of a cell on disk (see the module docstring); ``train_states`` resolves evaluation dependencies."""
    folder = cell_dir(cfg, cell)
    if not folder.exists():
        return CellStatus(cell, "todo")
    meta = _read_json(folder / CELL_JSON)
    done = (folder / DONE).is_file()
    if meta is None:
        return CellStatus(cell, "partial" if not done else "stale", "no cell.json", None)
    if meta.get("spec") != cell_spec(cfg, cell):
        changed = sorted(
            k
            for k in set(meta.get("spec") or {}) | set(cell_spec(cfg, cell))
            if (meta.get("spec") or {}).get(k) != cell_spec(cfg, cell).get(k)
        )
        return CellStatus(cell, "stale", "spec changed: " + ", ".join(changed), meta)
    if meta.get("weights", {}) != weights_fingerprint(cell.arm.predictor):
        return CellStatus(cell, "stale", "predictor weights changed", meta)
    if cell.needs is not None:
        train = (train_states or {}).get(cell.needs)
        if train is not None and train.state != "done":
            return CellStatus(cell, "stale" if done else "partial", f"waits for {cell.needs}", meta)
        model = trained_model(cell_dir(cfg, cell.needs), cell.policy.model)
        if done and (model is None or meta.get("model_sha256") != _file_sha256(model)):
            return CellStatus(cell, "stale", "the trained model changed", meta)
    if not done:
        return CellStatus(cell, "partial", "interrupted", meta)
    return CellStatus(cell, "done", "", meta)


def plan_on_disk(
    cfg: AblationConfig, cells: Sequence[Cell] | None = None
) -> tuple[list[CellStatus], dict[str, CellStatus]]:
    """States of ``cells`` (default: the whole grid) from their run folders alone, training cells resolved before their
    evaluations; and the states of every training cell of the grid (by name). :func:`agents.ablation.results.plan`
    adds the cells the committed results hold."""
    cells = list(expand(cfg) if cells is None else cells)
    train_states: dict[str, CellStatus] = {}
    for cell in expand(cfg):
        if cell.kind == "train":
            train_states[cell.name] = cell_status(cfg, cell)
    return [
        train_states[c.name] if c.kind == "train" else cell_status(cfg, c, train_states) for c in cells
    ], train_states


def select(cells: Sequence[Cell], patterns: str | None) -> list[Cell]:
    """Cells whose name matches one of the comma-separated glob ``patterns`` (plus the training cells
    their evaluations need); all cells without patterns."""
    if not patterns:
        return list(cells)
    pats = [p.strip() for p in patterns.split(",") if p.strip()]
    chosen = {c.name for c in cells if any(fnmatch.fnmatchcase(c.name, p) for p in pats)}
    chosen |= {c.needs for c in cells if c.name in chosen and c.needs is not None}
    if not chosen:
        raise ValueError(f"--only {patterns!r} matches no cell; cell names look like {cells[0].name!r}")
    return [c for c in cells if c.name in chosen]


#: Where a dry run's throughput comes from, in the order tried: finished cells in the grid's run folders, the
#: finished cells the committed results record (``cells.json``), the config's ``estimates``.
RATE_SOURCES: Final[tuple[str, ...]] = ("runs", "results", "config")

_RateKey = tuple[str, str, str]


def _pooled(samples: Mapping[_RateKey, list[float]]) -> dict[_RateKey, float]:
    """Cells of one key share their budget, so total work over total time is the harmonic mean of their rates."""
    return {k: len(v) / sum(1.0 / r for r in v) for k, v in samples.items() if v}


def _rate_arm(arm: Arm) -> str:
    """What a rate is kept per: the arm's source, or for an arm that plans with more (regions, samples: another cost)
    its label."""
    return arm.label if arm.variant else arm.predictor


def _rate(meta: Mapping[str, Any], kind: str) -> Any:
    """A finished cell's throughput from its ``cell.json`` or ``cells.json`` record: per CPU second where the cell
    recorded its CPU time (``steps_per_cpu_s`` / ``episodes_per_cpu_s``: its cost whatever shared the machine), else
    per wall second (cells from before CPU time was recorded; slower where other work shared the cores)."""
    if kind == "train":
        return meta.get("steps_per_cpu_s") or meta.get("steps_per_s")
    return meta.get("episodes_per_cpu_s") or meta.get("episodes_per_s")


def measured_rates(cfg: AblationConfig) -> dict[_RateKey, float]:
    """Throughput of the finished cells in the grid's run folders: ``(kind, policy kind, arm source) -> rate``
    (training: env steps, evaluation: episodes, per CPU second of the cell where recorded, else per wall second
    (:func:`_rate`); each cell's own ``cell.json``, the whole cell -- warm start, validation, every attempt --
    included), pooled as total work over total time. Uncertainty and samples arms are kept per arm label
    (:func:`_rate_arm`)."""
    samples: dict[_RateKey, list[float]] = {}
    root = cfg.runs_path()
    if not root.is_dir():
        return {}
    for path in root.glob(f"**/{CELL_JSON}"):
        meta = _read_json(path)
        if not meta or not (path.parent / DONE).is_file():
            continue
        spec = meta.get("spec") or {}
        rate = _rate(meta, "train" if spec.get("kind") == "train" else "eval")
        if isinstance(rate, int | float) and rate > 0:
            variant = "uncertainty" in spec or "samples" in spec
            arm = spec.get("arm") if variant else spec.get("predictor")
            key = (str(spec.get("kind")), str(spec.get("policy_kind")), str(arm))
            samples.setdefault(key, []).append(float(rate))
    return _pooled(samples)


def recorded_rates(cfg: AblationConfig) -> dict[_RateKey, float]:
    """Throughput of the finished cells the committed results record (``cells.json`` in ``cfg.out_path()``),
    keyed and pooled as :func:`measured_rates`; cells no longer in the grid are left out."""
    records = _read_json_list(cfg.out_path() / "cells.json")
    cells = {c.name: c for c in expand(cfg)}
    samples: dict[_RateKey, list[float]] = {}
    for rec in records:
        cell = cells.get(str(rec.get("cell")))
        rate = _rate(rec, "train" if cell is not None and cell.kind == "train" else "eval")
        if cell is None or rec.get("state") != "done" or not isinstance(rate, int | float) or rate <= 0:
            continue
        samples.setdefault((cell.kind, cell.policy.kind, _rate_arm(cell.arm)), []).append(float(rate))
    return _pooled(samples)


def _read_json_list(path: Path) -> list[dict[str, Any]]:
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return []
    return [r for r in data if isinstance(r, dict)] if isinstance(data, list) else []


def estimate_seconds(
    cfg: AblationConfig,
    cell: Cell,
    rates: Mapping[_RateKey, float],
    recorded: Mapping[_RateKey, float] | None = None,
) -> tuple[float, str]:
    """Estimated run time of a cell, seconds, and where its rate comes from (one of :data:`RATE_SOURCES`):
    ``rates`` (:func:`measured_rates`), else ``recorded`` (:func:`recorded_rates`), else the config's
    ``estimates`` (a training run's by ``<policy name>/<arm label>``, arm label, arm source, policy name, then
    ``default``: e.g. a policy with a slower teacher; an evaluation's by ``<policy name>/<arm label>``, arm label, policy
    name, policy kind, then ``default``)."""
    key = (cell.kind, cell.policy.kind, _rate_arm(cell.arm))
    if cell.kind == "train":
        work = float(cell.policy.timesteps or 0)
        defaults = cfg.train_steps_per_s
        keys = (f"{cell.policy.name}/{cell.arm.label}", cell.arm.label, cell.arm.predictor, cell.policy.name, "default")
        default = next((defaults[k] for k in keys if k in defaults), 1000.0)
    else:
        work = float(cfg.episodes)
        defaults = cfg.eval_episodes_per_s
        keys = (f"{cell.policy.name}/{cell.arm.label}", cell.arm.label, cell.policy.name, cell.policy.kind, "default")
        default = next((defaults[k] for k in keys if k in defaults), 2.0)
    for source, table in zip(RATE_SOURCES, (rates, recorded or {}), strict=False):
        if key in table:
            return work / table[key], source
    return work / default, "config"


def _hms(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def default_workers(cells: Iterable[Cell]) -> int:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    widest = max((c.cpus for c in cells), default=1)
    return max(1, cores // widest)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")
