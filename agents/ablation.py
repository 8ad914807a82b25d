"""The planning-aid ablation: forecast arms x policies x seeds x held-out splits, run as resumable cells.

``python -m agents.ablation configs/ablation/planning_aid.yaml [--dry-run] [--workers N]
[--backend local|ray] [--address ADDR] [--only PATTERN] [--summarize-only] [--replicate DIR]`` (also
``crowdnav-mesrnn ablation ...``).

The grid
    A YAML config (see ``configs/ablation/planning_aid.yaml``) names forecast arms (``none``, ``cv``,
    ``mesrnn``, ``srnn``, ``vlstm``, ``oracle``, and ``noisy_oracle`` expanded into one arm per target
    ADE), policies (learned ``ppo``/``sac`` with an agent config and a training budget; non-learned
    ``planner``/``straight``), training seeds, held-out splits and the fixed evaluation episode list.
    It expands into *cells*:

    - ``train/<split>/<policy>/<arm>/seed<k>``: one training run (``agents.train.train``) of a learned
      policy on the split's training scenes;
    - ``eval/<split>/<policy>/<arm>[/seed<k>]``: the trained model (its ``best`` or ``final`` model) or a
      planner evaluated with ``agents.evaluate.evaluate`` on the split's held-out scene over the fixed
      episode list (``evaluation.episodes`` episodes from ``evaluation.seed``), identical in every cell.

Cells and their state
    Every cell is a folder under ``runs_dir`` (default ``runs/ablation/<name>/``, gitignored) holding
    ``cell.json`` (what the cell is — its *spec* —, the predictor weights it used, timings) and, written
    last, ``DONE``. A cell is ``done`` (DONE present, spec and weights as now), ``stale`` (DONE present but its
    spec, the sha256 of the shipped predictor weights it used, or the model it evaluated changed: redone),
    ``partial`` (a folder without DONE: an interrupted run; a training cell resumes with
    ``train(..., resume=True)``, an evaluation cell is redone) or ``todo``. Re-running the grid skips done
    cells. ``--dry-run`` lists every cell with its state and an estimated time from measured throughputs
    (finished cells' ``cell.json``), falling back to the config's ``estimates``.
    ``--replicate DIR --only PATTERN`` runs the selected cells afresh in the scratch folder ``DIR`` and
    compares each replicated evaluation with the grid's, episode by episode (:func:`replicate`): cells are
    seeded, so a difference means nondeterminism or a change of behaviour since the grid's cell ran (only grid
    cells that are ``done`` are compared; the folder must be new or empty).

Backends
    ``local`` (default): a process pool (forkserver) of ``--workers`` processes (default: cores // the
    largest ``cpus`` of a cell), each with one torch thread; ``--workers 1`` runs cells one after the
    other in this process. ``ray``: the same cell function as Ray tasks (``ray.init(address=...)`` for an
    existing cluster, a local instance otherwise), ``num_cpus`` per task = the cell's ``cpus``. A Ray task
    does not need shared storage: the driver sends what the cell needs (an interrupted training run's folder,
    or the trained model being evaluated) with the task, the task works in a temporary folder on its node and
    returns the cell folder as a tar archive, which the driver writes into ``runs_dir``. Every node needs the
    project installed (``pip install 'crowdnav-mesrnn[ray]'``, the same version and predictor weights: a cell
    whose node has other weights than the driver fails and says so) and the ETH/UCY data at
    ``$CROWDNAV_MESRNN_DATA``; forecast caches are built per node on first use. On a cluster::

        CROWDNAV_MESRNN_DATA=/data/eth_ucy ray start --head --port=6379   # head node
        CROWDNAV_MESRNN_DATA=/data/eth_ucy ray start --address=HEAD:6379  # every other node
        python -m agents.ablation configs/ablation/planning_aid.yaml --backend ray --address HEAD:6379

    Without ``--address`` a local Ray instance with ``--workers`` x the largest ``cpus`` is started
    (no dashboard) and shut down at the end.

The answer
    :func:`summarize` reads the evaluation cells and writes ``summary.json``, ``summary.md`` and plots into
    ``out_dir`` (default ``results/ablation/<name>/``): rates with Wilson intervals and metric means with
    bootstrap intervals per policy and arm (pooled over splits and seeds, and per split), rates by crowd
    density bins, the pre-declared paired tests (exact McNemar on success, Wilcoxon signed-rank on the
    navigation time of episodes both arms finished, pairs = (training seed, episode)), Holm-corrected per
    endpoint with the family size stated, and the difference in success rate each McNemar design detects at
    the configured power.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import fnmatch
import hashlib
import io
import itertools
import json
import math
import os
import shutil
import socket
import sys
import tarfile
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from crowdnav_mesrnn.config import ConfigError, check_keys, load_yaml
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text, code_version

#: Forecast sources an arm may use.
ARM_SOURCES: Final[tuple[str, ...]] = ("none", "cv", "mesrnn", "srnn", "vlstm", "oracle", "noisy_oracle")
#: Sources that load shipped predictor weights (their sha256 is recorded per cell).
LEARNED_SOURCES: Final[tuple[str, ...]] = ("mesrnn", "srnn", "vlstm")
#: Policy kinds: learned ones are trained per arm and seed, the others only evaluated.
POLICY_KINDS: Final[tuple[str, ...]] = ("ppo", "sac", "planner", "straight")
LEARNED_KINDS: Final[tuple[str, ...]] = ("ppo", "sac")
#: Which model of a training run an evaluation cell uses.
MODEL_CHOICES: Final[tuple[str, ...]] = ("best", "final")
BACKENDS: Final[tuple[str, ...]] = ("local", "ray")
OUTCOMES: Final[tuple[str, ...]] = ("success", "collision", "timeout")
DONE: Final[str] = "DONE"
CELL_JSON: Final[str] = "cell.json"
TRAIN_RUN: Final[str] = "run"
AGENT_CONFIG: Final[str] = "agent_config.yaml"
CELL_STATES: Final[tuple[str, ...]] = ("done", "partial", "stale", "todo")

_TOP_KEYS: Final[tuple[str, ...]] = (
    "name",
    "description",
    "out_dir",
    "runs_dir",
    "splits",
    "arms",
    "noisy_oracle_ade_m",
    "seeds",
    "policies",
    "evaluation",
    "env",
    "comparisons",
    "policy_comparisons",
    "density_bins",
    "alpha",
    "power",
    "estimates",
)
_POLICY_KEYS: Final[tuple[str, ...]] = ("kind", "arms", "config", "timesteps", "n_envs", "cpus", "model", "overrides")
_EVAL_KEYS: Final[tuple[str, ...]] = ("episodes", "seed")
_ESTIMATE_KEYS: Final[tuple[str, ...]] = ("train_steps_per_s", "eval_episodes_per_s")


# ============================================================================ configuration


@dataclass(frozen=True)
class Arm:
    """One forecast arm: a forecast source, and for ``noisy_oracle`` its target ADE."""

    label: str
    """Name in cell paths and the summary (``mesrnn``, ``noisy_oracle-0.25``)."""
    predictor: str
    """Forecast source passed to the environment (one of :data:`ARM_SOURCES`)."""
    noisy_oracle_ade_m: float | None = None
    """Target ADE of ``noisy_oracle`` arms, metres."""

    def env_overrides(self) -> dict[str, Any]:
        """Environment keys this arm sets besides ``predictor``."""
        return {} if self.noisy_oracle_ade_m is None else {"noisy_oracle_ade_m": self.noisy_oracle_ade_m}


@dataclass(frozen=True)
class PolicySpec:
    """One policy of the grid (a key of ``policies:`` in the config)."""

    name: str
    """Its key in the config (``ppo``, ``planner``), used in cell paths and the summary."""
    kind: str
    """``ppo`` or ``sac`` (trained per arm and seed), ``planner`` or ``straight`` (evaluated only)."""
    config: str | None = None
    """Learned kinds: the agent YAML (``configs/agent/ppo.yaml``), relative to the working directory."""
    timesteps: int | None = None
    """Learned kinds: environment steps of training per run."""
    n_envs: int = 1
    """Learned kinds: vectorised environments per training run (the agent config's ``n_envs`` is replaced)."""
    cpus: int = 1
    """Learned kinds: CPUs a training run keeps busy (1 when the agent config steps its environments in one
    process, ``vec_env: dummy``; ``n_envs`` with subprocess workers); sizes the local pool and Ray's ``num_cpus``."""
    model: str = "best"
    """Learned kinds: ``best`` (selected on validation episodes of the training scenes) or ``final`` model."""
    overrides: Mapping[str, Any] = field(default_factory=dict)
    """Learned kinds: further overrides passed to ``agents.train.load_train_config``."""
    arms: tuple[str, ...] = ()
    """Arm labels this policy runs (empty = every arm of the grid); e.g. the cheap planner runs the
    noisy-oracle sweep while PPO trains only the main arms."""

    @property
    def learned(self) -> bool:
        return self.kind in LEARNED_KINDS

    def uses(self, arm: Arm) -> bool:
        return not self.arms or arm.label in self.arms


@dataclass(frozen=True)
class AblationConfig:
    """A grid (see ``configs/ablation/planning_aid.yaml``); load with :func:`load_config`."""

    name: str
    splits: tuple[str, ...]
    arms: tuple[Arm, ...]
    seeds: tuple[int, ...]
    policies: tuple[PolicySpec, ...]
    episodes: int
    """Evaluation episodes per cell (the fixed list of ``agents.evaluate.evaluation_seeds``)."""
    eval_seed: int = 0
    """Seed of the fixed evaluation episode list."""
    env: Mapping[str, Any] = field(default_factory=dict)
    """Environment overrides applied alike in every cell (training and evaluation)."""
    out_dir: str = ""
    runs_dir: str = ""
    comparisons: tuple[tuple[str, str], ...] = ()
    """Arm pairs tested within every policy and split, declared before any result exists."""
    policy_comparisons: tuple[tuple[str, str], ...] = ()
    """Policy pairs tested within every arm and split."""
    density_bins: int | tuple[float, ...] = 3
    """An integer = that many quantile bins of ``crowd_density`` over the fixed episode lists of all splits;
    a list = bin edges (pedestrians within sensor range)."""
    alpha: float = 0.05
    power: float = 0.8
    train_steps_per_s: Mapping[str, float] = field(default_factory=lambda: {"default": 1000.0})
    """Fallback training throughputs per arm label or source (``default`` for the others), env steps/s."""
    eval_episodes_per_s: Mapping[str, float] = field(default_factory=lambda: {"default": 2.0})
    """Fallback evaluation throughputs per policy kind (``default`` for the others), episodes/s."""
    description: str = ""
    source: str = ""
    """The YAML file it was read from."""

    @property
    def arm_labels(self) -> tuple[str, ...]:
        return tuple(a.label for a in self.arms)

    def policy(self, name: str) -> PolicySpec:
        return next(p for p in self.policies if p.name == name)

    def arm(self, label: str) -> Arm:
        return next(a for a in self.arms if a.label == label)

    def runs_path(self) -> Path:
        return Path(self.runs_dir or f"runs/ablation/{self.name}")

    def out_path(self) -> Path:
        return Path(self.out_dir or f"results/ablation/{self.name}")


def _bad(key: str, value: Any, allowed: str) -> ConfigError:
    return ConfigError(f"ablation config key {key!r}: got {value!r}; allowed: {allowed}")


def _str_list(raw: Mapping[str, Any], key: str, allowed: Sequence[str] | None = None) -> tuple[str, ...]:
    value = raw.get(key)
    allowed_text = ", ".join(allowed) if allowed else "a non-empty list of names"
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise _bad(key, value, f"a non-empty list of {allowed_text}" if allowed else allowed_text)
    for v in value:
        if allowed is not None and v not in allowed:
            raise _bad(key, v, allowed_text)
    if len(set(value)) != len(value):
        raise _bad(key, value, "a list without repeats")
    return tuple(value)


def _positive_int(value: Any, key: str, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise _bad(key, value, f"an integer >= {minimum}")
    return int(value)


def _rates(value: Any, key: str) -> dict[str, float]:
    if isinstance(value, int | float) and not isinstance(value, bool):
        value = {"default": value}
    if not isinstance(value, dict) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) and v > 0 for v in value.values()
    ):
        raise _bad(key, value, "a positive number or a mapping of names to positive numbers")
    return {str(k): float(v) for k, v in value.items()}


def _pairs(value: Any, key: str, names: Sequence[str]) -> tuple[tuple[str, str], ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise _bad(key, value, "a list of [a, b] pairs")
    out = []
    for pair in value:
        if not (isinstance(pair, list | tuple) and len(pair) == 2 and all(isinstance(v, str) for v in pair)):
            raise _bad(key, pair, "a pair [a, b] of names")
        for v in pair:
            if v not in names:
                raise _bad(key, v, ", ".join(names))
        if pair[0] == pair[1]:
            raise _bad(key, pair, "two different names")
        out.append((pair[0], pair[1]))
    return tuple(out)


def _noisy_label(ade: float) -> str:
    return f"noisy_oracle-{ade:g}"


def _policies(value: Any) -> tuple[PolicySpec, ...]:
    if not isinstance(value, dict) or not value:
        raise _bad("policies", value, "a mapping of policy names to {kind: ppo|sac|planner|straight, ...}")
    out = []
    for name, spec in value.items():
        where = f"policies.{name}"
        if not isinstance(spec, dict):
            raise _bad(where, spec, "a mapping with keys " + ", ".join(_POLICY_KEYS))
        check_keys(spec, _POLICY_KEYS, f"ablation config {where!r}")
        kind = spec.get("kind", name)
        if kind not in POLICY_KINDS:
            raise _bad(f"{where}.kind", kind, ", ".join(POLICY_KINDS))
        model = spec.get("model", "best")
        if model not in MODEL_CHOICES:
            raise _bad(f"{where}.model", model, ", ".join(MODEL_CHOICES))
        overrides = spec.get("overrides") or {}
        if not isinstance(overrides, dict):
            raise _bad(f"{where}.overrides", overrides, "a mapping")
        if kind in LEARNED_KINDS:
            config = spec.get("config")
            if not isinstance(config, str) or not config:
                raise _bad(f"{where}.config", config, "the path of an agent YAML (configs/agent/ppo.yaml)")
            timesteps = _positive_int(spec.get("timesteps"), f"{where}.timesteps")
            n_envs = _positive_int(spec.get("n_envs", 1), f"{where}.n_envs")
            cpus = _positive_int(spec.get("cpus", 1), f"{where}.cpus")
            out.append(PolicySpec(str(name), kind, config, timesteps, n_envs, cpus, model, overrides))
        else:
            extra = sorted(set(spec) & {"config", "timesteps", "n_envs", "cpus", "overrides"})
            if extra:
                raise _bad(f"{where}.{extra[0]}", spec[extra[0]], f"nothing: a {kind!r} policy is not trained")
            out.append(PolicySpec(str(name), kind))
    return tuple(out)


def _policy_arms(policy: PolicySpec, raw: Mapping[str, Any], arms: Sequence[Arm]) -> PolicySpec:
    """Resolve ``policies.<name>.arms`` (arm labels, or sources: ``noisy_oracle`` = the whole sweep)."""
    value = raw.get("arms")
    if value is None:
        return policy
    key = f"policies.{policy.name}.arms"
    names = [a.label for a in arms] + sorted({a.predictor for a in arms} - {a.label for a in arms})
    if not isinstance(value, list) or not value:
        raise _bad(key, value, "a non-empty list of " + ", ".join(names))
    chosen: list[str] = []
    for v in value:
        if v not in names:
            raise _bad(key, v, ", ".join(names))
        chosen += [a.label for a in arms if v in (a.label, a.predictor) and a.label not in chosen]
    return dataclasses.replace(policy, arms=tuple(chosen))


def config_from_mapping(raw: Mapping[str, Any], source: str = "") -> AblationConfig:
    """Validate a grid mapping (the YAML's content); every error is a :class:`ConfigError` naming the key."""
    check_keys(raw, _TOP_KEYS, "ablation config")
    name = raw.get("name")
    if not isinstance(name, str) or not name or any(c in name for c in "/\\ "):
        raise _bad("name", name, "a non-empty name without slashes or spaces")
    splits = _str_list(raw, "splits", SPLITS)
    sources = _str_list(raw, "arms", ARM_SOURCES)
    arms: list[Arm] = []
    for src in sources:
        if src != "noisy_oracle":
            arms.append(Arm(src, src))
            continue
        ades = raw.get("noisy_oracle_ade_m")
        if (
            not isinstance(ades, list)
            or not ades
            or not all(isinstance(v, int | float) and not isinstance(v, bool) and v >= 0 for v in ades)
        ):
            raise _bad("noisy_oracle_ade_m", ades, "a non-empty list of target ADEs >= 0 (metres) for arm noisy_oracle")
        if len(set(ades)) != len(ades):
            raise _bad("noisy_oracle_ade_m", ades, "a list without repeats")
        arms.extend(Arm(_noisy_label(float(v)), "noisy_oracle", float(v)) for v in ades)
    if "noisy_oracle_ade_m" in raw and "noisy_oracle" not in sources:
        raise _bad("noisy_oracle_ade_m", raw["noisy_oracle_ade_m"], "only with 'noisy_oracle' in arms")
    seeds = raw.get("seeds")
    if (
        not isinstance(seeds, list)
        or not seeds
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds)
        or len(set(seeds)) != len(seeds)
    ):
        raise _bad("seeds", seeds, "a non-empty list of distinct integers >= 0")
    policies = _policies(raw.get("policies"))
    labels = [a.label for a in arms]
    policies = tuple(_policy_arms(p, raw["policies"][p.name], arms) for p in policies)
    evaluation = raw.get("evaluation")
    if not isinstance(evaluation, dict):
        raise _bad("evaluation", evaluation, "a mapping {episodes: N, seed: S}")
    check_keys(evaluation, _EVAL_KEYS, "ablation config 'evaluation'")
    episodes = _positive_int(evaluation.get("episodes"), "evaluation.episodes")
    eval_seed = _positive_int(evaluation.get("seed", 0), "evaluation.seed", minimum=0)
    env = raw.get("env") or {}
    if not isinstance(env, dict):
        raise _bad("env", env, "a mapping of environment config keys")
    if "predictor" in env or "split" in env or "part" in env:
        raise _bad("env", env, "environment keys other than predictor, split and part (the grid sets those)")
    comparisons = _pairs(raw.get("comparisons"), "comparisons", labels)
    policy_comparisons = _pairs(raw.get("policy_comparisons"), "policy_comparisons", [p.name for p in policies])
    bins = raw.get("density_bins", 3)
    if isinstance(bins, list):
        if len(bins) < 2 or not all(isinstance(v, int | float) for v in bins) or list(bins) != sorted(set(bins)):
            raise _bad("density_bins", bins, "an integer >= 1 (quantile bins) or increasing bin edges")
        bins = tuple(float(v) for v in bins)
    else:
        bins = _positive_int(bins, "density_bins")
    alpha, power = raw.get("alpha", 0.05), raw.get("power", 0.8)
    for key, value in (("alpha", alpha), ("power", power)):
        if not isinstance(value, float) or not 0.0 < value < 1.0:
            raise _bad(key, value, "a number in (0, 1)")
    estimates = raw.get("estimates") or {}
    if not isinstance(estimates, dict):
        raise _bad("estimates", estimates, "a mapping with keys " + ", ".join(_ESTIMATE_KEYS))
    check_keys(estimates, _ESTIMATE_KEYS, "ablation config 'estimates'")
    for key in ("out_dir", "runs_dir", "description"):
        if not isinstance(raw.get(key, ""), str):
            raise _bad(key, raw[key], "a string")
    return AblationConfig(
        name=name,
        splits=splits,
        arms=tuple(arms),
        seeds=tuple(int(s) for s in seeds),
        policies=policies,
        episodes=episodes,
        eval_seed=eval_seed,
        env=dict(env),
        out_dir=raw.get("out_dir", ""),
        runs_dir=raw.get("runs_dir", ""),
        comparisons=comparisons,
        policy_comparisons=policy_comparisons,
        density_bins=bins,
        alpha=float(alpha),
        power=float(power),
        train_steps_per_s=_rates(estimates.get("train_steps_per_s", 1000.0), "estimates.train_steps_per_s"),
        eval_episodes_per_s=_rates(estimates.get("eval_episodes_per_s", 2.0), "estimates.eval_episodes_per_s"),
        description=str(raw.get("description", "")),
        source=source,
    )


def load_config(path: str | os.PathLike[str]) -> AblationConfig:
    """Read and validate a grid YAML (:class:`ConfigError` messages start with the file name)."""
    try:
        return config_from_mapping(load_yaml(path), source=str(path))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


# ============================================================================ cells


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
    """Every cell of the grid: training cells first, then evaluation cells (split, policy, arm, seed order)."""
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
    return train + evals


def _canonical_yaml_sha256(path: str) -> str | None:
    """sha256 of an agent YAML's parsed content (comments and layout do not count); None if missing."""
    try:
        content = load_yaml(path)
    except FileNotFoundError:
        return None
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
        "env": dict(sorted(cfg.env.items())),
    }
    if cell.kind == "train":
        spec.update(
            agent_config=cell.policy.config,
            agent_config_sha256=_canonical_yaml_sha256(cell.policy.config or ""),
            timesteps=cell.policy.timesteps,
            n_envs=cell.policy.n_envs,
            overrides=dict(cell.policy.overrides),
        )
    else:
        spec.update(episodes=cfg.episodes, eval_seed=cfg.eval_seed)
        if cell.policy.learned:
            spec["model"] = cell.policy.model
    return json.loads(json.dumps(spec, default=str))


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
    """sha256 of every shipped weights file an arm with this source uses (empty for sources without weights).

    A split's cells use the weights of all five splits: its held-out scene is forecast by its own
    split's predictor, each training scene by the predictor of the split holding that scene out.
    A missing file is recorded as ``"missing"``.
    """
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
    """The ``best``/``final`` model zip of a finished training cell folder (``None`` if absent)."""
    meta = _read_json(train_dir / CELL_JSON) or {}
    run = train_dir / meta.get("run_dir", TRAIN_RUN)
    for candidate in (run / f"{which}_model.zip", run / "final_model.zip"):
        if candidate.is_file():
            return candidate
    return None


@dataclass
class CellStatus:
    cell: Cell
    state: str
    reason: str = ""
    meta: dict[str, Any] | None = None


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


def plan(cfg: AblationConfig, cells: Sequence[Cell] | None = None) -> list[CellStatus]:
    """States of ``cells`` (default: the whole grid), training cells resolved before their evaluations."""
    cells = list(expand(cfg) if cells is None else cells)
    train_states: dict[str, CellStatus] = {}
    for cell in expand(cfg):
        if cell.kind == "train":
            train_states[cell.name] = cell_status(cfg, cell)
    return [train_states[c.name] if c.kind == "train" else cell_status(cfg, c, train_states) for c in cells]


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


# ============================================================================ throughput estimates


def measured_rates(cfg: AblationConfig) -> dict[tuple[str, str, str], float]:
    """Median measured throughput of finished cells: ``(kind, policy kind, arm source) -> rate``
    (training: env steps/s, evaluation: episodes/s)."""
    samples: dict[tuple[str, str, str], list[float]] = {}
    root = cfg.runs_path()
    if not root.is_dir():
        return {}
    for path in root.glob(f"**/{CELL_JSON}"):
        meta = _read_json(path)
        if not meta or not (path.parent / DONE).is_file():
            continue
        spec = meta.get("spec") or {}
        rate = meta.get("steps_per_s") if spec.get("kind") == "train" else meta.get("episodes_per_s")
        if isinstance(rate, int | float) and rate > 0:
            key = (str(spec.get("kind")), str(spec.get("policy_kind")), str(spec.get("predictor")))
            samples.setdefault(key, []).append(float(rate))
    return {k: float(np.median(v)) for k, v in samples.items()}


def estimate_seconds(cfg: AblationConfig, cell: Cell, rates: Mapping[tuple[str, str, str], float]) -> tuple[float, str]:
    """Estimated run time of a cell and where the rate comes from (``measured`` or ``default``)."""
    key = (cell.kind, cell.policy.kind, cell.arm.predictor)
    if cell.kind == "train":
        work = float(cell.policy.timesteps or 0)
        defaults = cfg.train_steps_per_s
        default = defaults.get(cell.arm.label, defaults.get(cell.arm.predictor, defaults.get("default", 1000.0)))
    else:
        work = float(cfg.episodes)
        defaults = cfg.eval_episodes_per_s
        default = defaults.get(cell.policy.name, defaults.get(cell.policy.kind, defaults.get("default", 2.0)))
    if key in rates:
        return work / rates[key], "measured"
    return work / default, "default"


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


def dry_run(cfg: AblationConfig, cells: Sequence[Cell], workers: int, out: Callable[[str], None] = print) -> None:
    """Print every cell with its state and estimated time, and the totals."""
    statuses = plan(cfg, cells)
    rates = measured_rates(cfg)

    def describe(p: PolicySpec) -> str:
        arms = f"arms {'/'.join(p.arms)}" if p.arms else "all arms"
        budget = f", {p.timesteps:,} steps x {p.n_envs} envs" if p.learned else ""
        return f"{p.name} ({p.kind}, {arms}{budget})"

    pol = "; ".join(describe(p) for p in cfg.policies)
    out(
        f"grid {cfg.name}: splits {', '.join(cfg.splits)}; arms {', '.join(cfg.arm_labels)}; "
        f"seeds {', '.join(map(str, cfg.seeds))}; policies {pol}; {cfg.episodes} evaluation episodes per cell"
    )
    out(f"cells in {cfg.runs_path()}/, summaries in {cfg.out_path()}/")
    out(f"{'state':<8} {'estimate':>9}  {'rate':<8} cell")
    total = 0.0
    counts = dict.fromkeys(CELL_STATES, 0)
    for st in statuses:
        counts[st.state] += 1
        secs, src = estimate_seconds(cfg, st.cell, rates)
        if st.state != "done":
            total += secs
        est = "-" if st.state == "done" else _hms(secs)
        reason = f"  ({st.reason})" if st.reason else ""
        out(f"{st.state:<8} {est:>9}  {src:<8} {st.cell.name}{reason}")
    n_train = sum(c.kind == "train" for c in cells)
    out(
        f"{len(cells)} cells ({n_train} train, {len(cells) - n_train} eval): "
        + ", ".join(f"{k} {v}" for k, v in counts.items())
    )
    out(
        f"estimated compute left {_hms(total)}; with {workers} worker(s) at a time, wall time >= {_hms(total / workers)} "
        "(evaluations wait for their training runs)"
    )


# ============================================================================ running one cell


@dataclass(frozen=True)
class CellTask:
    """What a worker needs to run one cell (picklable; paths are absolute or relative to the worker's cwd)."""

    cell: Cell
    folder: str
    spec: Mapping[str, Any]
    weights: Mapping[str, str]
    episodes: int
    eval_seed: int
    env: Mapping[str, Any]
    model: str | None = None
    """Evaluation of a learned policy: the model zip to evaluate."""
    model_sha256: str | None = None
    command: str = ""
    """The command line that reproduces the cell (recorded in a training run's ``command.txt``)."""
    agent_config: str | None = None
    """Training: the agent YAML's text (written into the cell as :data:`AGENT_CONFIG` and read from there,
    so a worker on another machine needs no copy of the driver's files)."""


def train_overrides(cell: Cell, env: Mapping[str, Any]) -> dict[str, Any]:
    """Overrides of ``agents.train.load_train_config`` for a training cell: the run (predictor, split,
    seed), the budget (``n_timesteps``, ``n_envs``), the grid's and the arm's environment settings
    (``env.<key>``), then the policy's own ``overrides``."""
    cell_env = {**dict(env), **cell.arm.env_overrides()}
    return {
        "predictor": cell.arm.predictor,
        "split": cell.split,
        "seed": cell.seed,
        "n_timesteps": cell.policy.timesteps,
        "n_envs": cell.policy.n_envs,
        **{f"env.{k}": v for k, v in sorted(cell_env.items())},
        **dict(cell.policy.overrides),
    }


def _run_train(task: CellTask, folder: Path) -> dict[str, Any]:
    """Train (or resume) one learned policy into ``folder / run``; returns counts for ``cell.json``."""
    from agents.train import load_train_config, train

    cfg = load_train_config(folder / AGENT_CONFIG, None, train_overrides(task.cell, task.env))
    run = folder / TRAIN_RUN
    result = train(cfg, run, resume=run.exists(), progress=False, command=task.command)
    return {
        "run_dir": Path(result).resolve().relative_to(folder.resolve()).as_posix(),
        "steps": task.cell.policy.timesteps,
    }


def _run_eval(task: CellTask, folder: Path) -> dict[str, Any]:
    """Evaluate a trained model or a planner on the held-out scene; writes episodes.csv and summary.json."""
    from agents.evaluate import evaluate

    cell = task.cell
    spec = task.model if cell.policy.learned else cell.policy.kind
    result = evaluate(
        spec,
        cell.arm.predictor,
        cell.split,
        task.episodes,
        seed=task.eval_seed,
        out_dir=folder,
        env_overrides={**task.env, **cell.arm.env_overrides()} or None,
    )
    rows = read_episodes(folder / "episodes.csv")
    steps = sum(int(float(r.get("steps", 0) or 0)) for r in rows) if rows and "steps" in rows[0] else None
    return {"episodes": int(result.get("episodes", len(rows))), "steps": steps}


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def execute_cell(task: CellTask) -> dict[str, Any]:
    """Run one cell in ``task.folder``: ``cell.json`` first, the work, then ``cell.json`` again and ``DONE``.

    Never raises for a failure of the work itself: the result (also in ``cell.json``) says ``ok`` and
    ``error``, so one failed cell does not stop the grid.
    """
    _single_thread()
    folder = Path(task.folder)
    folder.mkdir(parents=True, exist_ok=True)
    here = weights_fingerprint(task.cell.arm.predictor)
    if here != dict(task.weights):  # a Ray node with another installation than the driver's
        error = f"predictor weights on {socket.gethostname()} differ from the driver's: {here} != {dict(task.weights)}"
        return {"name": task.cell.name, "ok": False, "error": error, "wall_s": 0.0}
    old = _read_json(folder / CELL_JSON) or {}
    attempts = list(old.get("attempts", [])) if old.get("spec") == task.spec else []
    meta: dict[str, Any] = {
        "name": task.cell.name,
        "spec": dict(task.spec),
        "weights": dict(task.weights),
        "model": task.model,
        "model_sha256": task.model_sha256,
        "code_version": code_version(),
        "host": socket.gethostname(),
        "status": "running",
        "attempts": [*attempts, {"started": _now()}],
    }
    atomic_write_json(folder / CELL_JSON, meta)
    if task.agent_config is not None:
        atomic_write_text(folder / AGENT_CONFIG, task.agent_config)
    t0 = time.perf_counter()
    try:
        counts = _run_train(task, folder) if task.cell.kind == "train" else _run_eval(task, folder)
        ok, error = True, None
    except Exception as exc:  # report and carry on with the other cells
        counts, ok = {}, False
        error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"
    wall = time.perf_counter() - t0
    meta["attempts"][-1].update(finished=_now(), wall_s=round(wall, 3), ok=ok)
    meta.update(counts)
    meta["wall_s"] = round(sum(a.get("wall_s", 0.0) for a in meta["attempts"]), 3)
    meta["status"] = "done" if ok else "failed"
    meta["error"] = error
    if ok:
        if task.cell.kind == "train" and meta.get("steps"):
            meta["steps_per_s"] = meta["steps"] / max(meta["wall_s"], 1e-9)
        if task.cell.kind == "eval":
            meta["episodes_per_s"] = meta.get("episodes", task.episodes) / max(wall, 1e-9)
    atomic_write_json(folder / CELL_JSON, meta)
    if ok:
        atomic_write_text(folder / DONE, _now() + "\n")
    return {"name": task.cell.name, "ok": ok, "error": error, "wall_s": wall}


def _single_thread() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


# ============================================================================ backends


def _pack(folder: Path, arcname: str = ".", skip: Sequence[str] = ()) -> bytes:
    """A folder as gzipped tar bytes (``skip``: top-level names left out)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for path in sorted(folder.iterdir()) if folder.is_dir() else []:
            if path.name in skip:
                continue
            tar.add(path, arcname=f"{arcname}/{path.name}")
    return buf.getvalue()


def _unpack(blob: bytes, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(blob), mode="r:gz") as tar:
        tar.extractall(dest, filter="data")


def _replace_folder(folder: Path, blob: bytes) -> None:
    """Make ``folder`` hold exactly the archive's content, swapping it in with renames."""
    incoming = folder.parent / f".{folder.name}.incoming"
    old = folder.parent / f".{folder.name}.old"
    for tmp in (incoming, old):
        shutil.rmtree(tmp, ignore_errors=True)
    _unpack(blob, incoming)
    if folder.exists():
        folder.rename(old)
    incoming.rename(folder)
    shutil.rmtree(old, ignore_errors=True)


def execute_shipped(task: CellTask, inputs: bytes | None) -> tuple[dict[str, Any], bytes]:
    """A Ray task: run the cell in a temporary folder on this node and return its folder as tar bytes.

    ``inputs`` (tar bytes) holds ``cell/`` (an interrupted training run to resume) and/or ``model/`` (the
    trained run folder whose model is evaluated); paths in ``task`` are rewritten to the temporary copies.
    """
    with tempfile.TemporaryDirectory(prefix="crowdnav-ablation-") as tmp:
        root = Path(tmp)
        if inputs:
            _unpack(inputs, root)
        folder = root / "cell"
        model = None
        if task.model is not None:
            model = str(root / "model" / Path(task.model).name)
        local = dataclasses.replace(task, folder=str(folder), model=model)
        result = execute_cell(local)
        if task.model is not None:  # record the driver's path, not the temporary one
            meta = _read_json(folder / CELL_JSON) or {}
            meta["model"] = task.model
            atomic_write_json(folder / CELL_JSON, meta)
        return result, _pack(folder)


def _shipped_inputs(task: CellTask) -> bytes | None:
    buf = io.BytesIO()
    added = False
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        folder = Path(task.folder)
        if task.cell.kind == "train" and folder.is_dir():
            tar.add(folder, arcname="cell")
            added = True
        if task.model is not None:
            run = Path(task.model).parent
            for path in sorted(run.iterdir()):
                if path.is_file():  # the run's top-level files: models, resolved config; not checkpoints/logs
                    tar.add(path, arcname=f"model/{path.name}")
            added = True
    return buf.getvalue() if added else None


class _Backend:
    def submit(self, task: CellTask) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


class _Serial(_Backend):
    """Cells one after another in this process (``--workers 1``)."""

    def __init__(self) -> None:
        self._results: dict[int, dict[str, Any]] = {}
        self._next = 0

    def submit(self, task: CellTask) -> Any:
        self._next += 1
        self._results[self._next] = execute_cell(task)
        return self._next

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:
        handle = next(iter(handles))
        return handle, self._results.pop(handle)


class _Pool(_Backend):
    """A process pool with forkserver (or spawn) workers, one torch thread each."""

    def __init__(self, workers: int) -> None:
        import concurrent.futures as cf
        import multiprocessing as mp

        method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        self._cf = cf
        self._pool = cf.ProcessPoolExecutor(workers, mp_context=mp.get_context(method), initializer=_single_thread)

    def submit(self, task: CellTask) -> Any:
        return self._pool.submit(execute_cell, task)

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:
        done, _ = self._cf.wait(list(handles), return_when=self._cf.FIRST_COMPLETED)
        fut = next(iter(done))
        try:
            return fut, fut.result()
        except Exception as exc:  # a worker died (killed, out of memory): the cell stays partial
            return fut, {"ok": False, "error": f"worker failed: {type(exc).__name__}: {exc}"}

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class _Ray(_Backend):
    """Cells as Ray tasks; files travel with the task and its return value (no shared storage needed)."""

    def __init__(self, address: str | None, num_cpus: int | None) -> None:
        try:
            import ray
        except ImportError as exc:
            raise ConfigError(
                "--backend ray needs Ray: pip install 'crowdnav-mesrnn[ray]' (or pip install 'ray>=2.9')"
            ) from exc
        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True}
            if address:
                kwargs["address"] = address
                kwargs["runtime_env"] = {"env_vars": {"OMP_NUM_THREADS": "1"}}
            elif num_cpus:
                kwargs["num_cpus"] = num_cpus
            ray.init(**kwargs)
        self._remote = ray.remote(execute_shipped)
        self._tasks: dict[Any, CellTask] = {}

    def submit(self, task: CellTask) -> Any:
        ref = self._remote.options(num_cpus=task.cell.cpus, num_returns=1).remote(task, _shipped_inputs(task))
        self._tasks[ref] = task
        return ref

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:
        ready, _ = self._ray.wait(list(handles), num_returns=1)
        ref = ready[0]
        task = self._tasks.pop(ref)
        try:
            result, blob = self._ray.get(ref)
        except Exception as exc:  # the task itself died (node lost, worker killed)
            return ref, {"name": task.cell.name, "ok": False, "error": f"ray task failed: {type(exc).__name__}: {exc}"}
        _replace_folder(Path(task.folder), blob)
        return ref, result

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()


# ============================================================================ running the grid


def _prepare(cfg: AblationConfig, status: CellStatus) -> None:
    """Clear what must not be reused: stale cells, interrupted evaluations (interrupted training resumes)."""
    folder = cell_dir(cfg, status.cell)
    resumable = status.state == "partial" and status.cell.kind == "train" and status.meta is not None
    if status.state in ("stale", "partial") and not resumable and folder.exists():
        shutil.rmtree(folder)


def _task(cfg: AblationConfig, cell: Cell) -> CellTask:
    model = model_sha = None
    if cell.needs is not None:
        path = trained_model(cell_dir(cfg, cell.needs), cell.policy.model)
        if path is None:
            raise FileNotFoundError(f"{cell.needs} has no {cell.policy.model} model in {cell_dir(cfg, cell.needs)}")
        model, model_sha = str(path.resolve()), _file_sha256(path)
    return CellTask(
        cell=cell,
        folder=str(cell_dir(cfg, cell).resolve()),
        spec=cell_spec(cfg, cell),
        weights=weights_fingerprint(cell.arm.predictor),
        episodes=cfg.episodes,
        eval_seed=cfg.eval_seed,
        env=dict(cfg.env),
        model=model,
        model_sha256=model_sha,
        command=f"python -m agents.ablation {cfg.source or '<config>'} --only {cell.name}",
        agent_config=Path(cell.policy.config).read_text(encoding="utf-8") if cell.kind == "train" else None,
    )


def build_forecast_caches(
    cfg: AblationConfig, cells: Iterable[Cell], out: Callable[[str], None] = print
) -> list[tuple[str, str]]:
    """Build the shared on-disk forecast cache once for every (learned source, split) the cells need.

    Uses ``envs.forecasts.build_forecast_cache`` when the environment provides it (otherwise each process
    computes the forecasts it needs). Returns the pairs built.
    """
    import envs.forecasts as forecasts

    wanted = sorted({(c.arm.predictor, c.split) for c in cells if c.arm.predictor in LEARNED_SOURCES})
    build = getattr(forecasts, "build_forecast_cache", None)
    if not wanted:
        return []
    if build is None:
        out("note: envs.forecasts.build_forecast_cache is not available; every worker computes its own forecasts")
        return []
    for predictor, split in wanted:
        t0 = time.perf_counter()
        build(predictor, split=split, part="all")
        out(f"forecast cache {predictor}/{split} ready ({time.perf_counter() - t0:.1f} s)")
    return wanted


def run_grid(
    cfg: AblationConfig,
    *,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    only: str | None = None,
    summarize_after: bool = True,
    out: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run every cell that is not done (training before its evaluations) and summarise.

    Returns ``{"ran": [...], "failed": {name: error}, "skipped": [...], "wall_s": ...}``.
    """
    if backend not in BACKENDS:
        raise ConfigError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    t_start = time.perf_counter()
    cells = select(expand(cfg), only)
    workers = workers or default_workers(cells)
    statuses = plan(cfg, cells)
    todo = [s for s in statuses if s.state != "done"]
    out(f"grid {cfg.name}: {len(cells)} cells, {len(cells) - len(todo)} done, {len(todo)} to run ({backend} backend)")
    for policy in {s.cell.policy.name: s.cell.policy for s in todo if s.cell.policy.learned}.values():
        if not Path(policy.config or "").is_file():
            raise FileNotFoundError(f"policies.{policy.name}.config: agent config {policy.config!r} not found")
    for st in todo:
        _prepare(cfg, st)
    build_forecast_caches(cfg, [s.cell for s in todo], out=out)

    waiting = {s.cell.name: s.cell for s in todo}
    done_names = {s.cell.name for s in statuses if s.state == "done"}
    ran: list[str] = []
    failed: dict[str, str] = {}
    skipped: list[str] = []
    runner: _Backend
    if backend == "ray":
        widest = max((c.cpus for c in waiting.values()), default=1)
        runner = _Ray(address, num_cpus=None if address else workers * widest)
    elif workers <= 1:
        runner = _Serial()
    else:
        runner = _Pool(workers)
    running: dict[Any, Cell] = {}
    try:
        while waiting or running:
            ready = [c for c in waiting.values() if c.needs is None or c.needs in done_names]
            for cell in ready:
                del waiting[cell.name]
                out(f"start {cell.name}")
                running[runner.submit(_task(cfg, cell))] = cell
            if not running:  # what waits depends on failed cells
                skipped.extend(sorted(waiting))
                break
            handle, result = runner.wait_one(running)
            cell = running.pop(handle)
            if result.get("ok"):
                done_names.add(cell.name)
                ran.append(cell.name)
                out(f"done  {cell.name} ({_hms(float(result.get('wall_s', 0.0)))})")
            else:
                failed[cell.name] = str(result.get("error"))
                out(f"FAILED {cell.name}: {str(result.get('error')).splitlines()[0]}")
                for name in [n for n, c in waiting.items() if c.needs == cell.name]:
                    skipped.append(waiting.pop(name).name)
    finally:
        runner.close()
    wall = time.perf_counter() - t_start
    out(f"grid {cfg.name}: ran {len(ran)}, failed {len(failed)}, skipped {len(skipped)} in {_hms(wall)}")
    if summarize_after:
        summarize(cfg, out=out)
    return {"ran": ran, "failed": failed, "skipped": skipped, "wall_s": wall}


# ============================================================================ the summary


def read_episodes(path: str | os.PathLike[str]) -> list[dict[str, str]]:
    """Rows of an ``episodes.csv`` (empty if the file is missing)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            return list(csv.DictReader(fh))
    except FileNotFoundError:
        return []


def _num(value: str | None) -> float:
    try:
        return float(value) if value not in (None, "") else math.nan
    except ValueError:
        return math.nan


@dataclass
class _Episodes:
    """Evaluation episodes of one (policy, arm) pooled over cells: ``rows[i]`` (an ``episodes.csv`` row) is
    episode ``keys[i] = (split, training seed, episode index)``."""

    keys: list[tuple[str, int | None, int]] = field(default_factory=list)
    rows: list[Mapping[str, str]] = field(default_factory=list)

    def add(self, split: str, seed: int | None, rows: Sequence[Mapping[str, str]]) -> None:
        for i, row in enumerate(rows):
            self.keys.append((split, seed, int(_num(row.get("episode", str(i))))))
            self.rows.append(row)

    def subset(self, keep: Sequence[bool]) -> _Episodes:
        chosen = [i for i, b in enumerate(keep) if b]
        return _Episodes([self.keys[i] for i in chosen], [self.rows[i] for i in chosen])

    def outcome(self) -> np.ndarray:
        return np.asarray([str(r.get("outcome", "")) for r in self.rows], dtype=object)

    def metric(self, name: str) -> np.ndarray:
        return np.asarray([_num(r.get(name)) for r in self.rows], dtype=float)

    def __len__(self) -> int:
        return len(self.keys)


def aggregate(episodes: _Episodes) -> dict[str, Any]:
    """The evaluation's own aggregates (:func:`agents.evaluate.summarise`) of the pooled episodes: rates with
    Wilson intervals, metric means with bootstrap intervals (navigation time and path ratio over successful
    episodes; the forecast ADE is undefined in the ``none`` arm)."""
    from agents.evaluate import summarise

    return summarise(episodes.rows)


def _collect(cfg: AblationConfig) -> tuple[dict[tuple[str, str], _Episodes], dict[str, Any]]:
    """Episodes of every finished evaluation cell, keyed by (policy, arm); and which cells are missing."""
    pooled: dict[tuple[str, str], _Episodes] = {}
    missing: list[str] = []
    walls: dict[str, float] = {"train": 0.0, "eval": 0.0}
    starts: list[str] = []
    ends: list[str] = []
    statuses = plan(cfg)
    for st in statuses:
        if st.meta:
            for att in st.meta.get("attempts", []):
                starts.append(att.get("started", ""))
                ends.append(att.get("finished", ""))
        if st.state != "done":
            missing.append(st.cell.name)
            continue
        walls[st.cell.kind] += float((st.meta or {}).get("wall_s", 0.0))
        if st.cell.kind != "eval":
            continue
        rows = read_episodes(cell_dir(cfg, st.cell) / "episodes.csv")
        pooled.setdefault((st.cell.policy.name, st.cell.arm.label), _Episodes()).add(st.cell.split, st.cell.seed, rows)
    first = min((w for w in map(_when, starts) if w), default=None)
    last = max((w for w in map(_when, ends) if w), default=None)
    info = {
        "cells": [_cell_record(st) for st in statuses],
        "missing_cells": missing,
        "cell_wall_s": walls,
        "first_start": first.isoformat() if first else None,
        "last_finish": last.isoformat() if last else None,
        "span_s": (last - first).total_seconds() if first and last else None,
    }
    return pooled, info


def _cell_record(st: CellStatus) -> dict[str, Any]:
    """One line of ``cells.json``: a cell's state, cost and provenance."""
    meta = st.meta or {}
    rate = meta.get("steps_per_s") if st.cell.kind == "train" else meta.get("episodes_per_s")
    return {
        "cell": st.cell.name,
        "state": st.state,
        "wall_s": meta.get("wall_s"),
        "steps_per_s" if st.cell.kind == "train" else "episodes_per_s": None if rate is None else round(rate, 3),
        "code_version": meta.get("code_version"),
        "finished": (meta.get("attempts") or [{}])[-1].get("finished"),
        "weights_sha256": {k: v[:12] for k, v in (meta.get("weights") or {}).items()},
        "model_sha256": (meta.get("model_sha256") or "")[:12] or None,
    }


#: Leading columns of the results' combined ``episodes.csv.gz`` (the cell and the episode), then every
#: per-episode metric of :data:`agents.evaluate.METRICS`.
ARCHIVE_KEYS: Final[tuple[str, ...]] = ("policy", "arm", "split", "seed", "episode", "outcome")


def episodes_archive(pooled: Mapping[tuple[str, str], _Episodes]) -> bytes:
    """Every evaluated episode in one gzipped CSV (:data:`ARCHIVE_KEYS` and the metrics, 4 decimals;
    byte-identical for identical inputs), small enough to commit beside the summary so the tests can be
    redone without the runs."""
    import gzip

    from agents.evaluate import METRICS

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow((*ARCHIVE_KEYS, *METRICS))
    for (policy, arm), eps in sorted(pooled.items()):
        for (split, seed, ep), row in sorted(
            zip(eps.keys, eps.rows, strict=True), key=lambda kr: (kr[0][0], kr[0][1] or -1, kr[0][2])
        ):
            values = []
            for col in METRICS:
                x = _num(row.get(col))
                values.append("" if not math.isfinite(x) else f"{x:.4f}".rstrip("0").rstrip("."))
            writer.writerow([policy, arm, split, "" if seed is None else seed, ep, row.get("outcome", ""), *values])
    return gzip.compress(buf.getvalue().encode("utf-8"), mtime=0)


def _when(stamp: str | None) -> datetime.datetime | None:
    try:
        return datetime.datetime.fromisoformat(stamp) if stamp else None
    except ValueError:
        return None


def density_edges(cfg: AblationConfig, pooled: Mapping[tuple[str, str], _Episodes]) -> list[float]:
    """Crowd-density bin edges: the configured edges, or quantiles over the fixed episode list of every split.

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
    edges = np.unique(edges)
    return [float(e) for e in edges] if edges.size >= 2 else [float(values.min()), float(values.max())]


def _bin_index(density: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """Bin of each density: ``[e0, e1), [e1, e2), ..., [e_{k-1}, e_k]``; -1 outside."""
    e = np.asarray(edges)
    idx = np.searchsorted(e, density, side="right") - 1
    idx = np.where(density == e[-1], len(e) - 2, idx)
    return np.where((density < e[0]) | (density > e[-1]) | ~np.isfinite(density), -1, idx)


def by_density(episodes: _Episodes, edges: Sequence[float], confidence: float = 0.95) -> list[dict[str, Any]]:
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
        for o in OUTCOMES:
            k = int(np.sum(outcome[sel] == o))
            row[f"{o}_rate"] = k / n if n else math.nan
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
    a: _Episodes,
    b: _Episodes,
    keys: Sequence[tuple[int | None, int]],
    sa: np.ndarray,
    sb: np.ndarray,
    confidence: float,
) -> dict[str, Any] | None:
    """Welch's t-test on per-seed success rates over the paired episodes (the training seed as the unit);
    a side without seeds (a planner) is one fixed rate. ``None`` when neither side has seeds."""
    from agents.stats import welch_seed_test

    a_seeded = any(s is not None for _, s, _ in a.keys)
    b_seeded = any(s is not None for _, s, _ in b.keys)
    if not (a_seeded or b_seeded):
        return None
    seeds = np.asarray([-1 if s is None else s for s, _ in keys])
    groups = [seeds == s for s in np.unique(seeds)]

    def rates(success: np.ndarray, seeded: bool) -> list[float]:
        per = [float(success[g].mean()) for g in groups]
        return per if seeded else per[:1]  # a seedless side repeats the same episodes for every seed

    ra, rb = rates(sa, a_seeded), rates(sb, b_seeded)
    return {**welch_seed_test(ra, rb, confidence), "rates_a": ra, "rates_b": rb}


def paired_tests(
    cfg: AblationConfig, pooled: Mapping[tuple[str, str], _Episodes]
) -> tuple[list[dict[str, Any]], dict[str, int]]:
    """The declared comparisons: exact McNemar on success and Wilcoxon on navigation time (both succeeded),
    Holm-adjusted within each endpoint over every test performed; returns the tests and the family sizes."""
    from agents.stats import holm, mcnemar_exact, mcnemar_min_detectable_difference, wilcoxon_paired

    planned: list[tuple[str, str, str, str, str, str]] = []  # (policy_a, arm_a, policy_b, arm_b, split, kind)
    for policy in cfg.policies:
        for a, b in cfg.comparisons:
            if policy.uses(cfg.arm(a)) and policy.uses(cfg.arm(b)):
                planned += [(policy.name, a, policy.name, b, split, "arms") for split in cfg.splits]
    for p, q in cfg.policy_comparisons:
        for arm in cfg.arms:
            if cfg.policy(p).uses(arm) and cfg.policy(q).uses(arm):
                planned += [(p, arm.label, q, arm.label, split, "policies") for split in cfg.splits]
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
        mc = mcnemar_exact(sa, sb)
        seed_level = _seed_level(ea, eb, keys, sa, sb, 0.95)
        tests.append({**base, "endpoint": "success", **mc, **({"seed_level": seed_level} if seed_level else {})})
        both = sa & sb
        wx = wilcoxon_paired(ta[both], tb[both])
        tests.append({**base, "endpoint": "navigation_time_s", "population": "episodes both finished", **wx})
    families: dict[str, int] = {}
    for endpoint in ("success", "navigation_time_s"):
        members = [t for t in tests if t["endpoint"] == endpoint and not t.get("missing")]
        families[endpoint] = len(members)
        for t, adj in zip(members, holm([t["p_value"] for t in members]), strict=True):
            t["p_holm"] = adj
            t["family_size"] = len(members)
            t["significant"] = bool(adj <= cfg.alpha)
    seed_tests = [t["seed_level"] for t in tests if t.get("seed_level") and math.isfinite(t["seed_level"]["p_value"])]
    families["success_seed_level"] = len(seed_tests)
    for st, adj in zip(seed_tests, holm([st["p_value"] for st in seed_tests]), strict=True):
        st["p_holm"] = adj
        st["family_size"] = len(seed_tests)
        st["significant"] = bool(adj <= cfg.alpha)
    m = max(families.get("success", 0), 1)
    for t in tests:
        if t["endpoint"] == "success" and not t.get("missing"):
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


def summarize(cfg: AblationConfig, out: Callable[[str], None] = print, plots: bool = True) -> dict[str, Any]:
    """Write ``summary.json``, ``summary.md`` and the plots into ``cfg.out_path()``; returns the summary."""
    pooled, info = _collect(cfg)
    edges = density_edges(cfg, pooled)
    policies: dict[str, Any] = {}
    for policy in cfg.policies:
        arms: dict[str, Any] = {}
        for arm in cfg.arms:
            eps = pooled.get((policy.name, arm.label))
            if eps is None:
                continue
            entry: dict[str, Any] = {
                "predictor": arm.predictor,
                "noisy_oracle_ade_m": arm.noisy_oracle_ade_m,
                "seeds": sorted({s for _, s, _ in eps.keys if s is not None}),
                "splits": sorted({sp for sp, _, _ in eps.keys}),
                **aggregate(eps),
            }
            entry["by_split"] = {
                split: aggregate(eps.subset([k[0] == split for k in eps.keys])) for split in entry["splits"]
            }
            entry["by_density"] = by_density(eps, edges)
            arms[arm.label] = entry
        policies[policy.name] = {
            "kind": policy.kind,
            "timesteps": policy.timesteps,
            "n_envs": policy.n_envs if policy.learned else None,
            "model": policy.model if policy.learned else None,
            "agent_config": policy.config,
            "arms": arms,
        }
    tests, families = paired_tests(cfg, pooled)
    summary = {
        "name": cfg.name,
        "config": cfg.source,
        "code_version": code_version(),
        "generated": _now(),
        "splits": list(cfg.splits),
        "seeds": list(cfg.seeds),
        "episodes_per_cell": cfg.episodes,
        "evaluation_seed": cfg.eval_seed,
        "env": dict(cfg.env),
        "complete": not info["missing_cells"],
        "missing_cells": info["missing_cells"],
        "density_bins": edges,
        "policies": policies,
        "tests": tests,
        "multiple_comparisons": {
            "method": "Holm-Bonferroni within each endpoint",
            "alpha": cfg.alpha,
            "family_sizes": families,
        },
        "power": cfg.power,
        "wall_time": {
            "cells_s": info["cell_wall_s"],
            "first_start": info["first_start"],
            "last_finish": info["last_finish"],
            "span_s": info["span_s"],
        },
    }
    summary = _clean(summary)
    dest = cfg.out_path()
    dest.mkdir(parents=True, exist_ok=True)
    atomic_write_json(dest / "summary.json", summary)
    atomic_write_json(dest / "cells.json", _clean(info["cells"]))
    archive = episodes_archive(pooled)
    atomic_write(dest / "episodes.csv.gz", lambda fh: fh.write(archive))
    figures = write_plots(summary, dest) if plots else []
    atomic_write_text(dest / "summary.md", summary_markdown(summary, cfg, figures))
    out(f"wrote {dest}/: summary.json, summary.md, cells.json, episodes.csv.gz and {len(figures)} plot(s)")
    return summary


# ---------------------------------------------------------------------------- Markdown


def _pct(rate: Any, ci: Any) -> str:
    if rate is None:
        return "-"
    lo, hi = ci if ci else (None, None)
    bounds = f" [{100 * lo:.1f}, {100 * hi:.1f}]" if lo is not None and hi is not None else ""
    return f"{100 * rate:.1f}{bounds}"


def _mean(entry: Mapping[str, Any], metric: str, digits: int = 2) -> str:
    v = entry.get(f"{metric}_mean")
    if v is None:
        return "-"
    lo, hi = entry.get(f"{metric}_ci") or (None, None)
    bounds = f" [{lo:.{digits}f}, {hi:.{digits}f}]" if lo is not None and hi is not None else ""
    return f"{v:.{digits}f}{bounds}"


def _rate_table(entries: Mapping[str, Mapping[str, Any]], with_seeds: bool) -> list[str]:
    head = "| arm | " + ("seeds | " if with_seeds else "") + "episodes | success % | collision % | timeout % | "
    head += "nav. time s (successes) | path ratio (successes) | min gap m | forecast ADE m |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for arm, e in entries.items():
        seeds = (", ".join(map(str, e.get("seeds", []))) + " | ") if with_seeds else ""
        lines.append(
            f"| {arm} | {seeds}{e['episodes']} | {_pct(e['success_rate'], e['success_ci'])} | "
            f"{_pct(e['collision_rate'], e['collision_ci'])} | {_pct(e['timeout_rate'], e['timeout_ci'])} | "
            f"{_mean(e, 'navigation_time_s', 1)} | {_mean(e, 'path_ratio')} | {_mean(e, 'min_gap_m')} | "
            f"{_mean(e, 'forecast_ade_m')} |"
        )
    return lines


def _p(v: Any) -> str:
    if v is None:
        return "-"
    return f"{v:.2g}" if v < 0.001 else f"{v:.3f}"


def summary_markdown(summary: Mapping[str, Any], cfg: AblationConfig, figures: Sequence[str] = ()) -> str:
    """The human-readable report of :func:`summarize`."""
    lines = [f"# Ablation `{summary['name']}`", ""]
    if cfg.description:
        lines += [cfg.description.strip(), ""]
    lines += [
        f"Config `{summary['config']}`, code {summary['code_version']}, generated {summary['generated']}. "
        f"Held-out splits {', '.join(summary['splits'])}; {summary['episodes_per_cell']} evaluation episodes per "
        f"cell (episode list seed {summary['evaluation_seed']}, the same list in every cell of a split).",
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
    for name, pol in summary["policies"].items():
        lines += [f"### {name}", "", *_rate_table(pol["arms"], bool(pol["timesteps"])), ""]
        for split in summary["splits"] if len(summary["splits"]) > 1 else ():
            per = {a: e["by_split"][split] for a, e in pol["arms"].items() if split in e.get("by_split", {})}
            if per:
                lines += [f"{name} on `{split}`:", "", *_rate_table(per, False), ""]
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
    lines += [
        "## Paired tests",
        "",
        f"Declared in the config before any result: arm comparisons {', '.join(f'{a} vs {b}' for a, b in cfg.comparisons) or '(none declared)'} "
        f"within each policy and split; policy comparisons {', '.join(f'{a} vs {b}' for a, b in cfg.policy_comparisons) or '(none declared)'} "
        "within each arm and split. Pairs are (training seed, episode); a policy without seeds pairs its episode "
        "with that episode of every seed. Success: exact McNemar test (two-sided binomial test on the discordant "
        "pairs); navigation time: Wilcoxon signed-rank test over episodes both sides finished. "
        f"Holm-Bonferroni correction within each endpoint: {fam.get('success', 0)} success tests and "
        f"{fam.get('navigation_time_s', 0)} navigation-time tests; significant = Holm-adjusted p <= {mc['alpha']}.",
        "",
        f"Minimum detectable difference (MDD): the difference in success rate the McNemar design detects with "
        f"{100 * summary['power']:.0f} % power at the observed discordant fraction (Connor's 1987 normal "
        f"approximation), at alpha = {mc['alpha']} and at the strictest Holm level alpha / {max(fam.get('success', 0), 1)}; "
        "'-' where no difference the observed discordance allows reaches that power (or no pair is discordant).",
        "",
        "| split | a | b | n | b10 (a only) | b01 (b only) | success diff a-b [95 % CI] | p | p Holm | MDD | MDD Holm |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def side(s: Mapping[str, str]) -> str:
        return f"{s['policy']}/{s['arm']}"

    for t in summary["tests"]:
        if t["endpoint"] != "success":
            continue
        if t.get("missing"):
            lines.append(f"| {t['split']} | {side(t['a'])} | {side(t['b'])} | missing | | | | | | | |")
            continue
        lo, hi = t["difference_ci"]
        diff = f"{100 * t['difference']:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}]" if lo is not None else "-"
        mdd = "-" if t.get("mdd") is None else f"{100 * t['mdd']:.1f}"
        mddh = "-" if t.get("mdd_holm_strictest") is None else f"{100 * t['mdd_holm_strictest']:.1f}"
        star = " *" if t.get("significant") else ""
        lines.append(
            f"| {t['split']} | {side(t['a'])} | {side(t['b'])} | {t['n']} | {t['b10']} | {t['b01']} | {diff} | "
            f"{_p(t['p_value'])} | {_p(t['p_holm'])}{star} | {mdd} | {mddh} |"
        )
    seed_rows = [t for t in summary["tests"] if t["endpoint"] == "success" and t.get("seed_level")]
    if seed_rows:
        lines += [
            "",
            "Seed level (secondary): the McNemar test above is conditional on the trained policies, so it does not "
            "count the variance between training seeds. Here each training seed's success rate over the same paired "
            "episodes is one observation: Welch's t-test and 95 % t-interval on the difference of mean per-seed "
            "rates (a policy without seeds is one fixed rate, which makes it a one-sample test), Holm-corrected over "
            f"the {fam.get('success_seed_level', 0)} seed-level tests. With three seeds per arm these intervals are "
            "wide: a difference can be clear episode by episode and still undetermined across training seeds.",
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
        "Navigation time (s) of episodes both sides finished, a - b:",
        "",
        "| split | a | b | pairs | median diff | mean diff | p | p Holm |",
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


# ---------------------------------------------------------------------------- plots


def _err(entry: Mapping[str, Any], key: str) -> tuple[float, float, float]:
    rate = entry.get(f"{key}_rate")
    lo, hi = entry.get(f"{key}_ci") or (None, None)
    if rate is None or lo is None or hi is None:
        return (math.nan, 0.0, 0.0)
    return (rate, max(rate - lo, 0.0), max(hi - rate, 0.0))


def write_plots(summary: Mapping[str, Any], dest: Path) -> list[str]:
    """Rates per arm; success/collision against closed-loop forecast ADE; success by crowd density."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    policies = {k: v for k, v in summary["policies"].items() if v["arms"]}
    if not policies:
        return []
    written: list[str] = []
    colours = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:grey"}

    # one row pooled over splits, then one row per split (splits differ in difficulty, so pooling alone hides them)
    views: list[str | None] = [None, *summary["splits"]] if len(summary["splits"]) > 1 else [None]
    fig, axes = plt.subplots(
        len(views), len(policies), figsize=(5 * len(policies), 3.6 * len(views)), squeeze=False, sharey=True
    )
    for row, view in enumerate(views):
        for ax, (name, pol) in zip(axes[row], policies.items(), strict=True):
            entries = {a: (e if view is None else e.get("by_split", {}).get(view)) for a, e in pol["arms"].items()}
            arms = [a for a, e in entries.items() if e]
            x = np.arange(len(arms))
            for j, o in enumerate(OUTCOMES):
                vals = np.asarray([_err(entries[a], o) for a in arms]).reshape(-1, 3)
                ax.bar(x + (j - 1) * 0.27, vals[:, 0], 0.27, yerr=vals[:, 1:].T, color=colours[o], label=o, capsize=2)
            ax.set_xticks(x, arms, rotation=30, ha="right")
            ax.set_title(f"{name}, {'pooled over splits' if view is None else view}")
            ax.set_ylim(0, 1)
    written.append(_finish(fig, axes, dest / "rates_by_arm.png"))

    fig, axes = plt.subplots(1, len(policies), figsize=(5 * len(policies), 3.6), squeeze=False, sharey=True)
    for ax, (name, pol) in zip(axes[0], policies.items(), strict=True):
        for o in ("success", "collision"):
            pts = []
            for arm, e in pol["arms"].items():
                ade = e.get("forecast_ade_m_mean")
                if e["predictor"] == "oracle" and ade is None:
                    ade = 0.0
                r, lo, hi = _err(e, o)
                if ade is None:  # the none arm: a horizontal reference
                    ax.axhline(r, color=colours[o], ls=":", lw=1)
                    ax.annotate(f"{arm} ({o})", (0.0, r), fontsize=7, color=colours[o], va="bottom")
                    continue
                pts.append((ade, r, lo, hi, arm, e["predictor"]))
            pts.sort()
            if not pts:
                continue
            arr = np.asarray([p[:4] for p in pts], dtype=float)
            ax.errorbar(arr[:, 0], arr[:, 1], yerr=arr[:, 2:].T, fmt="o", color=colours[o], capsize=2, label=o)
            sweep = np.asarray([p[:2] for p in pts if p[5] in ("noisy_oracle", "oracle")], dtype=float)
            if len(sweep) > 1:
                ax.plot(sweep[:, 0], sweep[:, 1], "--", color=colours[o], lw=1)
            for ade, r, _, _, arm, _ in pts:
                ax.annotate(arm, (ade, r), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(name)
        ax.set_xlabel("closed-loop forecast ADE (m)")
        ax.set_ylim(0, 1)
    written.append(_finish(fig, axes, dest / "rates_vs_ade.png"))

    edges = summary.get("density_bins") or []
    if len(edges) >= 2:
        fig, axes = plt.subplots(2, len(policies), figsize=(5 * len(policies), 6), squeeze=False, sharey=True)
        labels = [f"{lo:.1f}-{hi:.1f}" for lo, hi in itertools.pairwise(edges)]
        for col, (name, pol) in enumerate(policies.items()):
            for row, o in enumerate(("success", "collision")):
                ax = axes[row][col]
                n_arms = max(len(pol["arms"]), 1)
                for k, (arm, e) in enumerate(pol["arms"].items()):
                    vals = np.asarray([_err(b, o) for b in e["by_density"]])
                    if vals.size == 0:
                        continue
                    x = np.arange(len(vals)) + (k - (n_arms - 1) / 2) * 0.8 / n_arms
                    ax.errorbar(x, vals[:, 0], yerr=vals[:, 1:].T, fmt="o-", capsize=2, label=arm, ms=3)
                ax.set_xticks(np.arange(len(labels)), labels)
                ax.set_ylim(0, 1)
                ax.set_title(f"{name}: {o}")
                if row == 1:
                    ax.set_xlabel("crowd density (pedestrians near the path)")
            if axes[0][col].get_legend_handles_labels()[0]:
                axes[0][col].legend(fontsize=7)
        axes[0][0].set_ylabel("success rate")
        axes[1][0].set_ylabel("collision rate")
        fig.tight_layout()
        written.append(str(_save(fig, dest / "rates_by_density.png")))
        plt.close(fig)
    return written


def _finish(fig: Any, axes: Any, path: Path) -> str:
    """Label and save a figure of rates (legends in the first row), then close it."""
    import matplotlib.pyplot as plt

    for row in axes:
        row[0].set_ylabel("rate (95 % Wilson CI)")
    for ax in axes[0]:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    saved = _save(fig, path)
    plt.close(fig)
    return str(saved)


def _save(fig: Any, path: Path) -> Path:
    return atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110))


# ============================================================================ command line


def replicate(
    cfg: AblationConfig,
    only: str,
    into: str | os.PathLike[str],
    workers: int | None = None,
    out: Callable[[str], None] = print,
) -> int:
    """Run the cells ``only`` selects (with the training runs their evaluations need) afresh in the empty
    scratch folder ``into``, then compare every replicated evaluation with the grid's own, episode by episode
    and column by column (outcome, times, distances, return, ...).

    Training and evaluation are seeded, so a replicate at the same code, seed and forecasts should give
    identical episodes; a difference points at nondeterminism or at a change of behaviour between the code
    that ran the grid's cell (``cells.json``) and this one. Only grid cells that are ``done`` (spec and
    weights as now) are compared. Returns the number of selected evaluations that failed, could not be
    compared, or differ.
    """
    cells = select(expand(cfg), only)  # adds the training run of every selected evaluation
    evals = [c for c in cells if c.kind == "eval"]
    if not evals:
        raise ConfigError(f"--only {only!r} selects no evaluation cell: there would be nothing to compare")
    into = Path(into).resolve()
    for own in (cfg.runs_path().resolve(), cfg.out_path().resolve()):
        if into.is_relative_to(own) or own.is_relative_to(into):
            raise ConfigError(
                f"--replicate {str(into)!r} overlaps the grid's folder {str(own)!r}; give a scratch folder"
            )
    if into.exists() and any(into.iterdir()):
        raise ConfigError(
            f"--replicate {str(into)!r} is not empty; give a new or empty folder (a replicate starts afresh)"
        )
    states = {st.cell.name: st for st in plan(cfg, evals)}
    scratch = dataclasses.replace(cfg, runs_dir=str(into / "runs"), out_dir=str(into / "results"))
    result = run_grid(scratch, workers=workers, only=",".join(c.name for c in cells), summarize_after=False, out=out)
    for name, error in result["failed"].items():
        out(f"failed: {name}\n{error}")
    differing = 0
    for cell in evals:
        grid = states[cell.name]
        ours = {(r.get("seed"), r["episode"]): r for r in read_episodes(cell_dir(scratch, cell) / "episodes.csv")}
        theirs = {(r.get("seed"), r["episode"]): r for r in read_episodes(cell_dir(cfg, cell) / "episodes.csv")}
        if grid.state != "done" or not theirs or not ours:
            why = f"the grid's cell is {grid.state}" + (f" ({grid.reason})" if grid.reason else "")
            out(
                f"{cell.name}: not compared: " + (why if grid.state != "done" or not theirs else "the replicate failed")
            )
            differing += 1
            continue
        columns = sorted(set(next(iter(ours.values()))) | set(next(iter(theirs.values()))))
        shared = sorted(set(ours) & set(theirs))
        same = sum(ours[k] == theirs[k] for k in shared)
        outcomes = sum(ours[k].get("outcome") == theirs[k].get("outcome") for k in shared)
        rate = {
            n: sum(e["outcome"] == "success" for e in side.values()) / len(side)
            for n, side in (("o", ours), ("t", theirs))
        }
        out(
            f"{cell.name}: {same}/{len(shared)} episodes identical in all {len(columns)} columns, "
            f"{outcomes}/{len(shared)} outcomes; {len(ours)} episodes here, {len(theirs)} in the grid; "
            f"success {100 * rate['o']:.1f} % here, {100 * rate['t']:.1f} % in the grid"
        )
        differing += same != len(shared) or len(ours) != len(theirs) or len(shared) != len(ours)
    return differing


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``python -m agents.ablation`` and ``crowdnav-mesrnn ablation``."""
    p.add_argument("config", help="grid YAML, e.g. configs/ablation/planning_aid.yaml")
    p.add_argument("--dry-run", action="store_true", help="list every cell with its state and estimated time")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="cells at a time (default: cores // the largest cpus of a cell; 1 = in this process)",
    )
    p.add_argument("--backend", choices=BACKENDS, default="local", help="local process pool (default) or Ray tasks")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (ray://host:10001 or host:6379; default: start a local Ray instance)",
    )
    p.add_argument("--only", default=None, help="comma-separated globs of cell names, e.g. 'eval/zara1/planner/*'")
    p.add_argument("--summarize-only", action="store_true", help="write summary.json/.md and plots from finished cells")
    p.add_argument(
        "--replicate",
        metavar="DIR",
        default=None,
        help="run the --only cells (and the training runs they need) afresh in scratch folder DIR and compare "
        "their evaluations with the grid's, episode by episode (a determinism and code-change check)",
    )


def run_from_args(args: argparse.Namespace) -> int:
    """Handler shared by both entry points; 1 when a cell failed."""
    cfg = load_config(args.config)
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    if args.address and args.backend != "ray":
        raise ConfigError("--address needs --backend ray")
    if args.replicate and (args.dry_run or args.summarize_only):
        raise ConfigError("--replicate cannot be combined with --dry-run or --summarize-only")
    if args.dry_run:
        cells = select(expand(cfg), args.only)
        dry_run(cfg, cells, args.workers or default_workers(cells))
        return 0
    if args.summarize_only:
        summarize(cfg)
        return 0
    if args.replicate:
        if not args.only:
            raise ConfigError("--replicate needs --only (the cells to replicate, e.g. 'eval/zara1/ppo/cv/seed1')")
        if args.backend != "local":
            raise ConfigError(f"--replicate runs on the local backend; got --backend {args.backend}")
        return 1 if replicate(cfg, args.only, args.replicate, args.workers) else 0
    result = run_grid(cfg, backend=args.backend, workers=args.workers, address=args.address, only=args.only)
    for name, error in result["failed"].items():
        print(f"failed: {name}\n{error}", file=sys.stderr)
    return 1 if result["failed"] or result["skipped"] else 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.ablation ...`` is ``crowdnav-mesrnn ablation ...`` (same parser, same error handling)."""
    from crowdnav_mesrnn.cli import main as cli_main

    return cli_main(["ablation", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
