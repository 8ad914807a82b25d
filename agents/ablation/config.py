"""The ablation's grid config: arms, policies, the frozen :class:`AblationConfig`, parsing and validation."""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from agents.ablation.archive import ARCHIVE_DIR, LEGACY_ARCHIVE, archive_name, has_archive
from agents.evaluation import EPISODE_SOURCES
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, check_keys, existing_config, load_yaml
from crowdnav_mesrnn.data.constants import SPLITS

#: Forecast sources an arm may use (besides predictor plug-ins), from the registry (:mod:`crowdnav_mesrnn.predictors`).
ARM_SOURCES: Final[tuple[str, ...]] = predictors.names(plugins=False)


#: Sources that load shipped predictor weights (their sha256 is recorded per cell).
LEARNED_SOURCES: Final[tuple[str, ...]] = predictors.names(predictors.PRETRAINED, plugins=False)


#: Suffix of an uncertainty arm: ``<source>_unc`` plans with the source's forecasts and their calibrated uncertainty
#: regions (the environment's ``forecast_uncertainty=True``, the planner's ``uncertainty=True``).
UNCERTAINTY_SUFFIX: Final[str] = "_unc"


#: Sources with an uncertainty arm: those whose regions are calibrated (:mod:`envs.forecasting.uncertainty`). Not
#: ``none`` (no forecast), ``oracle`` (its regions are 0: the arm would be the oracle arm again), ``noisy_oracle``
#: (its regions are the known noise, not a calibration) or plug-ins (no calibration).
UNCERTAINTY_SOURCES: Final[tuple[str, ...]] = predictors.names(
    predictors.BASELINE, predictors.PRETRAINED, plugins=False
) + predictors.names(predictors.FITTED_BASELINE, plugins=False)


#: Suffix of an online-region arm: ``<source>_unc_online`` is ``<source>_unc`` with the regions' thresholds tracked
#: inside each episode (the environment's ``forecast_uncertainty_method="online"``).
ONLINE_UNCERTAINTY_SUFFIX: Final[str] = "_unc_online"


#: Policy kinds with the ``uncertainty`` option (:mod:`agents.planners`), the only ones uncertainty arms run.
UNCERTAINTY_KINDS: Final[tuple[str, ...]] = ("planner", "search")


#: Suffix of a samples arm: ``<source>_samples`` plans against :data:`ARM_SAMPLES` sampled futures of each pedestrian
#: from the source's distribution (the environment's ``forecast_samples``, the search planner's ``samples=True``).
SAMPLES_SUFFIX: Final[str] = "_samples"


#: Sources with a samples arm: those with a distribution (``cv_gaussian``, the Gaussian heads of the structural RNNs;
#: :mod:`envs.forecasting.samples`).
SAMPLES_SOURCES: Final[tuple[str, ...]] = predictors.names(
    predictors.FITTED_BASELINE, predictors.PRETRAINED, plugins=False
)


#: Sampled futures per pedestrian of a samples arm (the environment's ``forecast_samples``): best-of-20's K.
ARM_SAMPLES: Final[int] = 20


#: Policy kinds with the ``samples`` option (:class:`agents.planners.SearchPlanner`), the only ones samples arms run.
SAMPLES_KINDS: Final[tuple[str, ...]] = ("search",)


#: Policy kinds: learned ones are trained per arm and seed, the others only evaluated.
POLICY_KINDS: Final[tuple[str, ...]] = ("ppo", "sac", "planner", "search", "privileged", "straight")

#: The privileged ceiling (reads the replay's true future, :mod:`agents.planners.privileged`): a measuring stick whose
#: success every other policy is also reported as a fraction of, never a competitor.
PRIVILEGED_KIND: Final[str] = "privileged"


LEARNED_KINDS: Final[tuple[str, ...]] = ("ppo", "sac")


#: A policy key ``<planner>@<reaction>`` (``search@orca``) names the reaction its environment sets (``policies.<key>.env:
#: {reaction: orca}``, issue 28): the summary's ``policies.search@orca.arms.<arm>.by_split`` then reads as "the search
#: planner among pedestrians who react by ORCA".
REACTION_SEPARATOR: Final[str] = "@"


#: Environment keys the grid sets in every cell itself (from ``arms``, ``splits``; evaluation on the held-out part).
GRID_ENV_KEYS: Final[tuple[str, ...]] = ("predictor", "split", "part")


#: Which model of a training run an evaluation cell uses.
MODEL_CHOICES: Final[tuple[str, ...]] = ("best", "final")


BACKENDS: Final[tuple[str, ...]] = ("local", "ray")


OUTCOMES: Final[tuple[str, ...]] = ("success", "collision", "timeout")


DONE: Final[str] = "DONE"


CELL_JSON: Final[str] = "cell.json"


TRAIN_RUN: Final[str] = "run"


AGENT_CONFIG: Final[str] = "agent_config.yaml"


CELL_STATES: Final[tuple[str, ...]] = ("done", "partial", "stale", "todo")


#: A grid's committed results (``out_dir``): every cell's record (``cells.json``) and every evaluated episode, values as
#: written (``episodes/``, one file per policy: :mod:`agents.ablation.archive`); :mod:`agents.ablation.results`.
RESULTS_CELLS: Final[str] = "cells.json"
#: The older single episode archive's name (:data:`agents.ablation.archive.LEGACY_ARCHIVE`), kept for imports written
#: before the archive became ``episodes/``; readers still accept that file.
RESULTS_ARCHIVE: Final[str] = LEGACY_ARCHIVE


#: ``test_unit`` values (:attr:`AblationConfig.test_unit`).
TEST_UNITS: Final[tuple[str, ...]] = ("pair", "episode")

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
    "reaction_comparisons",
    "disturbance_comparisons",
    "density_bins",
    "alpha",
    "power",
    "test_unit",
    "estimates",
    "reuse",
)


_POLICY_KEYS: Final[tuple[str, ...]] = (
    "kind",
    "arms",
    "config",
    "timesteps",
    "n_envs",
    "cpus",
    "model",
    "overrides",
    "options",
    "env",
    "priority",
)


_EVAL_KEYS: Final[tuple[str, ...]] = ("episodes", "seed", "episodes_from")


#: ``evaluation.episodes_from``: ``test`` (the default), every evaluation cell on the split's held-out scene; ``val``,
#: on the split's training scenes in their validation period (a pilot: choices are made there, never on a held-out
#: scene; :data:`agents.evaluation.EPISODE_SOURCES`).
EPISODES_FROM: Final[tuple[str, ...]] = tuple(EPISODE_SOURCES)


_ESTIMATE_KEYS: Final[tuple[str, ...]] = ("train_steps_per_s", "eval_episodes_per_s")


#: Training overrides the grid sets in every cell (and where a config sets them instead).
_GRID_OVERRIDES: Final[dict[str, str]] = {
    "predictor": "arms",
    "split": "splits",
    "seed": "seeds",
    "n_timesteps": "policies.<name>.timesteps",
    "n_envs": "policies.<name>.n_envs",
}


@dataclass(frozen=True)
class Arm:
    """One forecast arm: a forecast source, for ``noisy_oracle`` its target ADE, and whether it plans with the
    forecasts' uncertainty regions (split or online thresholds) or with sampled futures."""

    label: str
    """Name in cell paths and the summary (``mesrnn``, ``noisy_oracle-0.25``, ``mesrnn_unc``)."""
    predictor: str
    """Forecast source passed to the environment (one of :data:`ARM_SOURCES`, or a predictor plug-in)."""
    noisy_oracle_ade_m: float | None = None
    """Target ADE of ``noisy_oracle`` arms, metres."""
    uncertainty: bool = False
    """An uncertainty arm (``<source>_unc``, source in :data:`UNCERTAINTY_SOURCES`): the environment adds the
    forecasts' calibrated uncertainty radii (``forecast_uncertainty=True``) and the planner keeps clear of the
    regions (``uncertainty=True``)."""
    uncertainty_method: str = "split"
    """The regions' thresholds (the environment's ``forecast_uncertainty_method``): ``online`` for
    ``<source>_unc_online``."""
    samples: int = 0
    """A samples arm (``<source>_samples``, source in :data:`SAMPLES_SOURCES`): this many sampled futures per pedestrian
    in the observation (``forecast_samples``), planned against by the search planner (``samples=True``)."""

    @property
    def variant(self) -> bool:
        """The arm plans with more than its source's forecasts (regions or samples): a source's name never names it."""
        return self.uncertainty or self.samples > 0

    def env_overrides(self) -> dict[str, Any]:
        """Environment keys this arm sets besides ``predictor``."""
        out: dict[str, Any] = {} if self.noisy_oracle_ade_m is None else {"noisy_oracle_ade_m": self.noisy_oracle_ade_m}
        if self.uncertainty:
            out["forecast_uncertainty"] = True
            if self.uncertainty_method != "split":
                out["forecast_uncertainty_method"] = self.uncertainty_method
        if self.samples:
            out["forecast_samples"] = self.samples
        return out

    def planner_options(self) -> dict[str, Any]:
        """Planner options this arm sets (on top of the policy's ``options``)."""
        if self.samples:
            return {"samples": True}
        return {"uncertainty": True} if self.uncertainty else {}

    def spec(self) -> dict[str, Any]:
        """What a cell's spec and the summary say of the arm beyond its source: only the keys of the variant it is
        (none for a point arm, so the specs of every other arm stay as they were): its environment keys, renamed."""
        return {_VARIANT_SPEC[k]: v for k, v in self.env_overrides().items() if k in _VARIANT_SPEC}


#: The environment keys of an uncertainty or samples arm -> their names in a cell's spec and the summary.
_VARIANT_SPEC: Final[dict[str, str]] = {
    "forecast_uncertainty": "uncertainty",
    "forecast_uncertainty_method": "uncertainty_method",
    "forecast_samples": "samples",
}


@dataclass(frozen=True)
class PolicySpec:
    """One policy of the grid (a key of ``policies:`` in the config)."""

    name: str
    """Its key in the config (``ppo``, ``planner``), used in cell paths and the summary."""
    kind: str
    """``ppo`` or ``sac`` (trained per arm and seed); ``planner`` (sampling), ``search``, ``privileged`` (the
    ceiling: reads the true future) or ``straight`` (evaluated only)."""
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
    """Learned kinds: further overrides passed to ``agents.training.config.load_train_config``."""
    options: Mapping[str, Any] = field(default_factory=dict)
    """Planner kinds: the planner's options (``agents.evaluation.run.evaluate``'s ``planner_kwargs``, e.g. the sampling
    planner's ``candidates: dense``); part of the cell's spec."""
    arms: tuple[str, ...] = ()
    """Arm labels this policy runs (empty = every arm of the grid); e.g. the cheap planner runs the
    noisy-oracle sweep while PPO trains only the main arms."""
    env: Mapping[str, Any] = field(default_factory=dict)
    """Planner kinds: environment settings of this policy's cells on top of the grid's ``env`` (e.g. ``{reaction:
    orca}``), passed to the environment and part of every cell's spec (:meth:`AblationConfig.env_for`). A policy that
    sets ``reaction`` is keyed ``<planner>@<reaction>``."""
    priority: int = 0
    """When this policy's cells run: lower first, then by split in the order of ``splits`` (so an interrupted grid
    has its most informative cells); the order of running is not part of any cell's spec."""

    @property
    def learned(self) -> bool:
        return self.kind in LEARNED_KINDS

    @property
    def base(self) -> str:
        """The planner a ``<planner>@<reaction>`` key names (``search`` for ``search@orca``; the key itself otherwise)."""
        return self.name.split(REACTION_SEPARATOR, 1)[0]

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
    """Evaluation episodes per cell (the fixed list of ``agents.rollout.evaluation_seeds``)."""
    eval_seed: int = 0
    """Seed of the fixed evaluation episode list."""
    episodes_from: str = "test"
    """Which episodes every evaluation cell replays (:data:`EPISODES_FROM`): ``test``, the split's held-out scene;
    ``val``, its training scenes' validation period (``part="train"``, ``episode_time="val"``), for pilots whose
    choices must not see a held-out scene. Part of an evaluation cell's spec only when ``val`` (the specs of every
    grid before it stay as they were)."""
    env: Mapping[str, Any] = field(default_factory=dict)
    """Environment overrides applied alike in every cell (training and evaluation)."""
    out_dir: str = ""
    runs_dir: str = ""
    reuse: tuple[str, ...] = ()
    """Other grids' committed results folders (``results/ablation/planners``; relative to the working directory, like
    ``out_dir``), in the order they are tried: a cell without a run folder whose done record there has this grid's
    spec and predictor weights is done, read from there (:mod:`agents.ablation.results`). Not part of any cell's
    spec."""
    comparisons: tuple[tuple[str, str], ...] = ()
    """Arm pairs tested within every policy and split, declared before any result exists."""
    policy_comparisons: tuple[tuple[str, str], ...] = ()
    """Policy pairs tested within every arm and split."""
    reaction_comparisons: tuple[tuple[str, str], ...] = ()
    """Reaction pairs ``(r, baseline)``: for every planner run under both (``<planner>@r``, ``<planner>@baseline``) and
    every arm pair of ``comparisons`` (a gain), the change of the gain from ``baseline`` to ``r`` on the same episodes
    (:func:`agents.ablation.stats.reaction_tests`)."""
    disturbance_comparisons: tuple[tuple[str, str], ...] = ()
    """Arm pairs whose disturbance metrics (:data:`agents.rollout.DISTURBANCE_METRICS`) are compared within every
    policy whose pedestrians react (:func:`agents.ablation.stats.disturbance_tests`)."""
    density_bins: int | tuple[float, ...] = 3
    """An integer = that many quantile bins of ``crowd_density`` over the fixed episode lists of all splits;
    a list = bin edges (pedestrians within sensor range)."""
    alpha: float = 0.05
    power: float = 0.8
    test_unit: str = "pair"
    """The unit of a paired test where a side has training seeds (:data:`TEST_UNITS`). ``pair`` (the default, every
    grid declared before ``learned_v2``): two seeded policies pair (seed, episode) and are tested by exact McNemar,
    navigation time by Wilcoxon over (seed, episode) pairs (against a planner too). ``episode``: the episode is the
    unit, since the seeds replay the same episodes and which episodes one side wins repeats across seeds: success by
    the exact sign-flip test of each episode's successes summed over the seeds (as a seeded policy against a planner
    already is in both), navigation time by Wilcoxon over each episode's mean difference over the seeds both sides
    finished (:func:`agents.ablation.stats.paired_tests`). Two policies without seeds are tested alike in both."""
    train_steps_per_s: Mapping[str, float] = field(default_factory=lambda: {"default": 1000.0})
    """Fallback training throughputs per ``<policy name>/<arm label>``, arm label, arm source or policy name, looked up
    in that order (``default`` for the others), env steps/s."""
    eval_episodes_per_s: Mapping[str, float] = field(default_factory=lambda: {"default": 2.0})
    """Fallback evaluation throughputs per ``<policy name>/<arm label>``, arm label, policy name or policy kind, looked
    up in that order (``default`` for the others), episodes/s."""
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

    def env_for(self, policy: PolicySpec) -> dict[str, Any]:
        """The environment settings of a policy's cells: the grid's ``env``, then the policy's own (:func:`resolve_env`:
        with a ``reaction``, ``reaction_params`` holds every parameter). Equal to ``env`` for a policy without one."""
        return resolve_env({**self.env, **policy.env})

    def reaction(self, policy: PolicySpec) -> str | None:
        """The reaction model of a policy's pedestrians (``None``: the environment's default, the replay)."""
        return (dict(self.env) | dict(policy.env)).get("reaction")

    def episodes_described(self) -> str:
        """Which episodes the evaluation cells replay, in words (the summary names them, so that no one reads a pilot on
        validation episodes as a held-out result)."""
        if self.episodes_from == "test":
            return f"the held-out scene of each split ({', '.join(self.splits)})"
        from envs.config import CrowdNavConfig

        fraction = float(self.env.get("val_fraction", CrowdNavConfig.val_fraction))
        return (
            f"validation episodes of the training scenes of {', '.join(self.splits)} (part train, episode_time val: the "
            f"last {fraction:g} of each training recording's duration); no held-out scene is replayed, so these are "
            "pilot figures for choices, not held-out results"
        )

    def runs_path(self) -> Path:
        return Path(self.runs_dir or f"runs/ablation/{self.name}")

    def out_path(self) -> Path:
        return Path(self.out_dir or f"results/ablation/{self.name}")


def _bad(key: str, value: Any, allowed: str) -> ConfigError:
    return ConfigError(f"ablation config key {key!r}: got {value!r}; allowed: {allowed}")


def _reuse(value: Any, out_dir: Path) -> tuple[str, ...]:
    """``reuse``: a list of other grids' results folders, each existing and holding :data:`RESULTS_CELLS` and an episode
    archive (:func:`agents.ablation.archive.has_archive`), none the grid's own ``out_dir``. Raises :class:`ConfigError`
    naming the key, the value and what is allowed (or the missing file)."""
    if value is None:
        return ()
    allowed = (
        "a list of other grids' committed results folders, relative to the working directory (e.g. "
        f"[results/ablation/planners]), each holding {RESULTS_CELLS} and {ARCHIVE_DIR}/ (or the older {LEGACY_ARCHIVE})"
    )
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise _bad("reuse", value, allowed)
    if len(set(value)) != len(value):
        raise _bad("reuse", value, "a list without repeats")
    for folder in value:
        path = Path(folder)
        if not path.is_dir():
            raise _bad("reuse", folder, f"{allowed}; there is no folder {folder!r}")
        if path.resolve() == out_dir.resolve():
            raise _bad(
                "reuse", folder, f"folders other than the grid's own out_dir ({out_dir}: it is read first anyway)"
            )
        if not (path / RESULTS_CELLS).is_file():
            raise _bad("reuse", folder, f"{allowed}; {path / RESULTS_CELLS} is missing")
        if not has_archive(path):
            raise _bad("reuse", folder, f"{allowed}; {path / ARCHIVE_DIR}/ is missing")
    return tuple(value)


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


def resolve_env(env: Mapping[str, Any]) -> dict[str, Any]:
    """``env`` with, when it sets ``reaction``, ``reaction_params`` resolved to every parameter: the defaults of
    ``envs.reaction.ReactionParams`` with the given overrides (``ReactionParams.to_dict()``), so that a cell's spec
    names every constant of its reaction model and a changed default makes its cells stale. Without ``reaction`` the
    mapping is returned as it is (the specs of grids without reactions stay as they were)."""
    out = dict(env)
    if "reaction" in out:
        from envs.reaction import ReactionParams

        out["reaction_params"] = ReactionParams.from_mapping(out.get("reaction_params")).to_dict()
    return out


def _env_mapping(value: Any, where: str) -> dict[str, Any]:
    """An ``env`` mapping (the grid's or a policy's) checked for what the grid decides itself: a mapping of string keys,
    none of :data:`GRID_ENV_KEYS`. Every other key is the environment's to check (:func:`check_environments`)."""
    if value is None:
        return {}
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise _bad(where, value, "a mapping of environment config keys")
    if set(value) & set(GRID_ENV_KEYS):
        raise _bad(where, value, "environment keys other than predictor, split and part (the grid sets those)")
    return dict(value)


def _check_reaction(env: Mapping[str, Any], where: str) -> None:
    """``reaction`` one of ``envs.reaction.REACTION_MODELS`` and ``reaction_params`` overrides of its parameters (only
    with a ``reaction``), each error naming the key (``where.reaction``, ``where.reaction_params``)."""
    from envs.reaction import ReactionParams, check_model

    for key, check in (("reaction", check_model), ("reaction_params", ReactionParams.from_mapping)):
        if key not in env:
            continue
        if key == "reaction_params" and "reaction" not in env:
            raise _bad(f"{where}.{key}", env[key], "only with a reaction (reaction: pause, orca or social_force)")
        try:
            check(env[key])
        except ConfigError as exc:
            raise ConfigError(f"ablation config key {where + '.' + key!r}: {exc}") from None


def _check_policy_env(policy: PolicySpec, grid_env: Mapping[str, Any]) -> None:
    """A policy's environment: its reaction settings (with the grid's) are valid, and its key names its reaction --
    ``<planner>@<reaction>`` exactly when the policy sets ``reaction`` (or names one the grid's ``env`` sets)."""
    where = f"policies.{policy.name}.env"
    merged = {**grid_env, **policy.env}
    _check_reaction(merged, where)
    reaction = merged.get("reaction")
    if REACTION_SEPARATOR in policy.name:
        named = policy.name.split(REACTION_SEPARATOR, 1)[1]
        if named != reaction:
            raise _bad(
                f"policies.{policy.name}",
                dict(policy.env),
                f"a policy keyed <planner>@<reaction> sets that reaction: env: {{reaction: {named}}} (here the "
                f"reaction is {reaction!r})",
            )
    elif "reaction" in policy.env:
        raise _bad(
            f"{where}.reaction",
            reaction,
            f"a policy key that names it: {policy.name}{REACTION_SEPARATOR}{reaction} (the summary's key of this "
            "policy then says which pedestrians it met)",
        )


def _check_planner_options(policy: PolicySpec, grid_env: Mapping[str, Any]) -> None:
    """Build the planner with its options (``agents.planners.make_planner``) in the policy's environment settings (the
    grid's ``env``, then the policy's own, on the environment's defaults), so an option the planner does not know --
    e.g. one another change has not implemented yet -- or one its environment does not allow (the privileged reactive
    ceiling under ``reaction: none``) is refused when the grid is loaded, naming ``policies.<name>.options``; settings
    the environment refuses are named as ``policies.<name>.env`` (or ``env``)."""
    if not policy.options:
        return
    from agents.planners import as_env_config, make_planner

    try:
        env_config = as_env_config({**grid_env, **policy.env})
    except ConfigError as exc:
        where = f"policies.{policy.name}.env" if policy.env else "env"
        raise ConfigError(f"ablation config key {where!r}: the environment refuses these settings: {exc}") from None
    try:
        make_planner(policy.kind, env_config, **dict(policy.options))
    except (TypeError, ValueError) as exc:
        raise _bad(
            f"policies.{policy.name}.options",
            dict(policy.options),
            f"options the {policy.kind!r} planner takes ({exc})",
        ) from None


def _noisy_label(ade: float) -> str:
    return f"noisy_oracle-{ade:g}"


#: Longest file name (bytes) of a policy's episode archive file (``episodes/<name>.csv.gz``, percent-encoded): file
#: systems allow 255, and an atomic write adds a temporary suffix.
MAX_ARCHIVE_NAME_BYTES: Final[int] = 200


def _policy_name(name: Any) -> None:
    """A policy name a grid can run: a non-empty string without ``/`` whose archive file name fits
    :data:`MAX_ARCHIVE_NAME_BYTES` -- checked when the config loads, not after hours of cells."""
    if not isinstance(name, str) or not name.strip() or "/" in name:
        raise _bad("policies", name, "policy names that are non-empty strings without '/' (they name cells and files)")
    if len(archive_name(name).encode()) > MAX_ARCHIVE_NAME_BYTES:
        raise _bad(
            "policies",
            name,
            f"a shorter policy name: its episode file name {archive_name(name)!r} would exceed "
            f"{MAX_ARCHIVE_NAME_BYTES} bytes",
        )


def _policies(value: Any) -> tuple[PolicySpec, ...]:
    if not isinstance(value, dict) or not value:
        raise _bad("policies", value, "a mapping of policy names to {kind: " + "|".join(POLICY_KINDS) + ", ...}")
    out = []
    for name, spec in value.items():
        where = f"policies.{name}"
        _policy_name(name)
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
        priority = spec.get("priority", 0)
        if isinstance(priority, bool) or not isinstance(priority, int):
            raise _bad(f"{where}.priority", priority, "an integer (lower runs first)")
        if kind in LEARNED_KINDS:
            if "env" in spec:
                raise _bad(
                    f"{where}.env",
                    spec["env"],
                    "nothing: a learned policy's environment is its agent config's and the grid's env (it is trained "
                    "there too)",
                )
            config = spec.get("config")
            if not isinstance(config, str) or not config:
                raise _bad(f"{where}.config", config, "the path of an agent YAML (configs/agent/ppo.yaml)")
            timesteps = _positive_int(spec.get("timesteps"), f"{where}.timesteps")
            n_envs = _positive_int(spec.get("n_envs", 1), f"{where}.n_envs")
            cpus = _positive_int(spec.get("cpus", 1), f"{where}.cpus")
            if "options" in spec:
                raise _bad(f"{where}.options", spec["options"], "nothing: a learned policy takes overrides")
            out.append(
                PolicySpec(str(name), kind, config, timesteps, n_envs, cpus, model, overrides, priority=priority)
            )
        else:
            extra = sorted(set(spec) & {"config", "timesteps", "n_envs", "cpus", "overrides"})
            if extra:
                raise _bad(f"{where}.{extra[0]}", spec[extra[0]], f"nothing: a {kind!r} policy is not trained")
            options = spec.get("options") or {}
            if not isinstance(options, dict) or not all(isinstance(k, str) for k in options):
                raise _bad(f"{where}.options", options, "a mapping of the planner's option names to values")
            if "uncertainty" in options:
                raise _bad(
                    f"{where}.options.uncertainty",
                    options["uncertainty"],
                    f"nothing: an uncertainty arm sets it ({', '.join(s + UNCERTAINTY_SUFFIX for s in UNCERTAINTY_SOURCES)})",
                )
            if "samples" in options:
                raise _bad(
                    f"{where}.options.samples",
                    options["samples"],
                    f"nothing: a samples arm sets it ({', '.join(s + SAMPLES_SUFFIX for s in SAMPLES_SOURCES)})",
                )
            env = _env_mapping(spec.get("env"), f"{where}.env")
            out.append(PolicySpec(str(name), kind, options=dict(options), env=env, priority=priority))
    return tuple(out)


def _policy_arms(policy: PolicySpec, raw: Mapping[str, Any], arms: Sequence[Arm]) -> PolicySpec:
    """Resolve ``policies.<name>.arms`` (arm labels, or sources: ``noisy_oracle`` = the whole sweep)."""
    value = raw.get("arms")
    if value is None:
        return policy
    key = f"policies.{policy.name}.arms"
    labels = [a.label for a in arms]
    # a source that is not itself an arm's label names every arm of that source (the noisy-oracle sweep); never
    # an uncertainty or samples arm, which is named by its label only
    names = labels + sorted({a.predictor for a in arms if not a.variant} - set(labels))
    if not isinstance(value, list) or not value:
        raise _bad(key, value, "a non-empty list of " + ", ".join(names))
    chosen: list[str] = []
    for v in value:
        if v not in names:
            raise _bad(key, v, ", ".join(names))
        chosen += [
            a.label
            for a in arms
            if (v == a.label or (v not in labels and v == a.predictor and not a.variant)) and a.label not in chosen
        ]
    return dataclasses.replace(policy, arms=tuple(chosen))


def _check_uncertainty_arms(policies: Sequence[PolicySpec], arms: Sequence[Arm]) -> None:
    """Uncertainty arms run only policies with the planners' ``uncertainty`` option (:data:`UNCERTAINTY_KINDS`), samples
    arms only those with the ``samples`` option (:data:`SAMPLES_KINDS`): learned policies are not trained on the
    regions or samples (out of scope), and straight-to-goal and the privileged ceiling do not read forecasts. Raises
    :class:`ConfigError` naming ``policies.<name>.arms``."""
    for policy in policies:
        for what, kinds, chosen in (
            ("uncertainty", UNCERTAINTY_KINDS, [a.label for a in arms if a.uncertainty and policy.uses(a)]),
            ("samples", SAMPLES_KINDS, [a.label for a in arms if a.samples and policy.uses(a)]),
        ):
            if not chosen or policy.kind in kinds:
                continue
            plain = [a.label for a in arms if not a.variant]
            plan_with = "uncertainty regions" if what == "uncertainty" else "sampled futures"
            why = (
                f"a learned {policy.kind!r} policy is not trained with {plan_with} (out of scope)"
                if policy.learned
                else f"a {policy.kind!r} policy does not plan with {plan_with}"
            )
            raise _bad(
                f"policies.{policy.name}.arms",
                list(policy.arms) or "every arm",
                f"arms without the {what} arms {', '.join(chosen)}: {why}; only the {' and '.join(kinds)} "
                f"kind{'s' if len(kinds) > 1 else ''} run{'' if len(kinds) > 1 else 's'} them. List this policy's arms, "
                f"e.g. arms: [{', '.join(plain)}]",
            )


def training_overrides(
    policy: PolicySpec, arm: Arm, split: str, seed: int | None, env: Mapping[str, Any]
) -> dict[str, Any]:
    """Overrides of ``agents.training.config.load_train_config`` for one training run of the grid: the run (predictor,
    split, seed), the budget (``n_timesteps``, ``n_envs``), the grid's and the arm's environment settings
    (``env.<key>``), then the policy's own ``overrides`` (which may not set the keys before them)."""
    cell_env = {**dict(env), **arm.env_overrides()}
    return {
        "predictor": arm.predictor,
        "split": split,
        "seed": seed,
        "n_timesteps": policy.timesteps,
        "n_envs": policy.n_envs,
        **{f"env.{k}": v for k, v in sorted(cell_env.items())},
        **dict(policy.overrides),
    }


def _did_you_mean(message: str, overrides: Mapping[str, Any]) -> str:
    """`` (did you mean 'pretrain.episodes'?)``: the dotted override key of the training config's suggestion in
    ``message`` (an "unknown ... key 'x'; did you mean 'y'? (valid keys: ...)" of
    :func:`crowdnav_mesrnn.config.check_keys`), so the user reads the key as written in the grid's YAML."""
    found = re.search(r"key '([^']+)'; did you mean '([^']+)'\?", message)
    if not found:
        return ""
    word, close = found.groups()
    key = next((k for k in overrides if k == word or k.endswith(f".{word}")), word)
    return f" (did you mean {key[: len(key) - len(word)] + close!r}?)"


def _check_training(policies: Sequence[PolicySpec], arms: Sequence[Arm], split: str, seed: int, env: Mapping) -> None:
    """Load the training config of every learned policy with each forecast source it trains on, as a cell
    would (``agents.training.config.load_train_config``), so a wrong override or agent config fails now, not when the
    cell starts. Raises :class:`ConfigError` naming ``policies.<name>``."""
    for policy in (p for p in policies if p.learned):
        where = f"policies.{policy.name}"
        for key in policy.overrides:
            if key in _GRID_OVERRIDES:
                raise _bad(
                    f"{where}.overrides.{key}",
                    policy.overrides[key],
                    f"nothing: the grid sets {key!r} (from {_GRID_OVERRIDES[key].replace('<name>', policy.name)})",
                )
        if not Path(policy.config or "").is_file():
            raise _bad(f"{where}.config", policy.config, "an existing agent YAML (relative to the working directory)")
        from agents.training.config import load_train_config

        seen: set[str] = set()
        for arm in (a for a in arms if policy.uses(a)):
            if arm.predictor in seen:
                continue
            seen.add(arm.predictor)
            try:
                load_train_config(policy.config, None, training_overrides(policy, arm, split, seed, env))
            except ConfigError as exc:
                raise ConfigError(
                    f"ablation config key {where + '.overrides'!r} (with agent config {policy.config}, arm "
                    f"{arm.label}): {exc}{_did_you_mean(str(exc), policy.overrides)}"
                ) from None


def _check_selection_seed(
    policies: Sequence[PolicySpec], arms: Sequence[Arm], split: str, seed: int, env: Mapping, eval_seed: int
) -> None:
    """On validation episodes (``evaluation.episodes_from: val``), refuse an episode list that is a learned policy's own
    validation list (its agent config's ``eval.seed``): training selects its ``best`` model on those very episodes, so
    the pilot would score each run on the episodes it was picked on. Raises :class:`ConfigError` naming
    ``evaluation.seed``."""
    from agents.training.config import load_train_config

    for policy in (p for p in policies if p.learned):
        arm = next(a for a in arms if policy.uses(a))
        selected_on = load_train_config(
            policy.config, None, training_overrides(policy, arm, split, seed, env)
        ).eval.seed
        if selected_on == eval_seed:
            raise _bad(
                "evaluation.seed",
                eval_seed,
                f"a seed other than {selected_on}: with episodes_from: val it is the validation list policy "
                f"{policy.name!r} selects its best model on ({policy.config}: eval.seed {selected_on})",
            )


def _variant_arm(src: str) -> Arm | None:
    """The uncertainty, online-region or samples arm ``src`` names; None for a forecast source or a predictor plug-in
    (crowdnav-mesrnn bench's arm). Raises :class:`ConfigError` naming ``arms`` and the arms allowed for anything else."""
    if src in ARM_SOURCES or predictors.is_plugin(src):
        return None
    unc_names = ", ".join(s + UNCERTAINTY_SUFFIX for s in UNCERTAINTY_SOURCES)
    for suffix, sources in (
        (ONLINE_UNCERTAINTY_SUFFIX, UNCERTAINTY_SOURCES),
        (UNCERTAINTY_SUFFIX, UNCERTAINTY_SOURCES),
        (SAMPLES_SUFFIX, SAMPLES_SOURCES),
    ):
        base = src.removesuffix(suffix)
        if base == src:
            continue
        if base in sources:
            if suffix == SAMPLES_SUFFIX:
                return Arm(src, base, samples=ARM_SAMPLES)
            method = "online" if suffix == ONLINE_UNCERTAINTY_SUFFIX else "split"
            return Arm(src, base, uncertainty=True, uncertainty_method=method)
        if suffix == SAMPLES_SUFFIX:
            names = ", ".join(s + SAMPLES_SUFFIX for s in SAMPLES_SOURCES)
            raise _bad("arms", src, f"samples arms {names} ({base!r} has no distribution to sample)")
        why = {
            "none": "none has no forecast to be uncertain about",
            "oracle": f"the oracle's regions are 0, so oracle{suffix} would be the oracle arm again",
            "noisy_oracle": "the noisy oracle's regions are its known noise, not a calibration",
        }.get(base, f"{base!r} has no calibrated regions")
        names = ", ".join(s + suffix for s in UNCERTAINTY_SOURCES)
        raise _bad(
            "arms",
            src,
            f"{'online-region' if suffix == ONLINE_UNCERTAINTY_SUFFIX else 'uncertainty'} arms {names} ({why})",
        )
    raise _bad(
        "arms",
        src,
        ", ".join(ARM_SOURCES)
        + f", an uncertainty arm ({unc_names}), an online-region arm (<source>{ONLINE_UNCERTAINTY_SUFFIX}, the same "
        f"sources), a samples arm ({', '.join(s + SAMPLES_SUFFIX for s in SAMPLES_SOURCES)}), an installed predictor "
        "plug-in or package.module:Factory",
    )


def config_from_mapping(raw: Mapping[str, Any], source: str = "") -> AblationConfig:
    """Validate a grid mapping (the YAML's content); every error is a :class:`ConfigError` naming the key."""
    check_keys(raw, _TOP_KEYS, "ablation config")
    name = raw.get("name")
    if not isinstance(name, str) or not name or any(c in name for c in "/\\ "):
        raise _bad("name", name, "a non-empty name without slashes or spaces")
    splits = _str_list(raw, "splits", SPLITS)
    sources = _str_list(raw, "arms")
    arms: list[Arm] = []
    for src in sources:
        variant = _variant_arm(src)
        if variant is not None:
            arms.append(variant)
            continue
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
    _check_uncertainty_arms(policies, arms)
    evaluation = raw.get("evaluation")
    if not isinstance(evaluation, dict):
        raise _bad("evaluation", evaluation, "a mapping {episodes: N, seed: S, episodes_from: test|val}")
    check_keys(evaluation, _EVAL_KEYS, "ablation config 'evaluation'")
    episodes = _positive_int(evaluation.get("episodes"), "evaluation.episodes")
    eval_seed = _positive_int(evaluation.get("seed", 0), "evaluation.seed", minimum=0)
    episodes_from = evaluation.get("episodes_from", "test")
    if episodes_from not in EPISODES_FROM:
        raise _bad(
            "evaluation.episodes_from",
            episodes_from,
            "test (the split's held-out scene) or val (its training scenes' validation period)",
        )
    env = _env_mapping(raw.get("env") or {}, "env")
    _check_reaction(env, "env")
    for policy in policies:
        _check_policy_env(policy, env)
        _check_planner_options(policy, env)
    comparisons = _pairs(raw.get("comparisons"), "comparisons", labels)
    policy_comparisons = _pairs(raw.get("policy_comparisons"), "policy_comparisons", [p.name for p in policies])
    reactions = [r for r in dict.fromkeys((dict(env) | dict(p.env)).get("reaction") for p in policies) if r]
    reaction_comparisons = _pairs(raw.get("reaction_comparisons"), "reaction_comparisons", reactions)
    if reaction_comparisons and not comparisons:
        raise _bad(
            "reaction_comparisons",
            raw["reaction_comparisons"],
            "nothing without comparisons (the gains whose change across reactions is tested)",
        )
    disturbance_comparisons = _pairs(raw.get("disturbance_comparisons"), "disturbance_comparisons", labels)
    bins = raw.get("density_bins", 3)
    if isinstance(bins, list):
        if len(bins) < 2 or not all(isinstance(v, int | float) for v in bins) or list(bins) != sorted(set(bins)):
            raise _bad("density_bins", bins, "an integer >= 1 (quantile bins) or increasing bin edges")
        bins = tuple(float(v) for v in bins)
    else:
        bins = _positive_int(bins, "density_bins")
    test_unit = raw.get("test_unit", "pair")
    if test_unit not in TEST_UNITS:
        raise _bad("test_unit", test_unit, ", ".join(TEST_UNITS))
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
    reuse = _reuse(raw.get("reuse"), Path(raw.get("out_dir") or f"results/ablation/{name}"))
    _check_training(policies, arms, splits[0], int(seeds[0]), env)
    if episodes_from == "val":
        _check_selection_seed(policies, arms, splits[0], int(seeds[0]), env, eval_seed)
    return AblationConfig(
        name=name,
        splits=splits,
        arms=tuple(arms),
        seeds=tuple(int(s) for s in seeds),
        policies=policies,
        episodes=episodes,
        eval_seed=eval_seed,
        episodes_from=episodes_from,
        env=dict(env),
        out_dir=raw.get("out_dir", ""),
        runs_dir=raw.get("runs_dir", ""),
        reuse=reuse,
        comparisons=comparisons,
        policy_comparisons=policy_comparisons,
        reaction_comparisons=reaction_comparisons,
        disturbance_comparisons=disturbance_comparisons,
        density_bins=bins,
        alpha=float(alpha),
        power=float(power),
        test_unit=str(test_unit),
        train_steps_per_s=_rates(estimates.get("train_steps_per_s", 1000.0), "estimates.train_steps_per_s"),
        eval_episodes_per_s=_rates(estimates.get("eval_episodes_per_s", 2.0), "estimates.eval_episodes_per_s"),
        description=str(raw.get("description", "")),
        source=source,
    )


def load_config(path: str | os.PathLike[str]) -> AblationConfig:
    """Read and validate a grid YAML (:class:`ConfigError` messages start with the file name)."""
    path = existing_config(path, "ablation")  # a missing file lists the grids under configs/ablation/
    try:
        return config_from_mapping(load_yaml(path), source=str(path))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
