"""A training run's configuration: the YAML layout, its loading with overrides, and the algorithm it builds.

RL Zoo's layout: one top-level entry per environment id holding the algorithm's hyperparameters
(``n_envs``, ``n_timesteps``, ``policy``, ``policy_kwargs``, ``normalize`` and the algorithm's own
keyword arguments), so the same file works with ``python -m rl_zoo3.train --algo ppo --env
CrowdNav-MESRNN-v0 --gym-packages crowdnav_mesrnn -conf configs/agent/ppo.yaml``. Settings of this
project live under the separate top-level key ``crowdnav_mesrnn`` (:data:`agents.runs.PROJECT_KEY`; RL Zoo
reads only the entry of the environment id it trains): ``algo``, ``env`` (environment settings, e.g. reward
weights, ``time_penalty``, ``observe_time_left``), ``train_env``/``val_env`` (on top of ``env`` for training or
validation episodes only), ``eval``, ``checkpoint_freq_steps``, ``keep_checkpoints``, ``vec_env``, ``pretrain``
(behaviour-cloning warm start, :mod:`agents.training.pretrain`) and ``action`` (``kind: continuous``, or
``discrete`` for the goal-relative velocities of :mod:`agents.actions`, PPO only). Everything is read with
``yaml.safe_load``; nothing is evaluated: ``policy_kwargs`` is a mapping (activation functions by name, see
:mod:`agents.extractors`), learning-rate schedules are RL Zoo's ``lin_<initial>`` strings.

The forecast arm chooses the entry: ``mesrnn`` -> ``CrowdNav-MESRNN-v0``, ``none`` -> ``CrowdNav-NoPred-v0``,
``cv`` -> ``CrowdNav-CV-v0``, ``oracle`` -> ``CrowdNav-Oracle-v0``; ``srnn``, ``vlstm``, ``noisy_oracle`` and
predictor plug-ins use the ``CrowdNav-MESRNN-v0`` entry with their own predictor.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from agents.actions import action_set
from agents.planners import PLANNERS
from agents.runs import PROJECT_KEY
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, check_keys, existing_config, load_yaml, replace_checked
from crowdnav_mesrnn.data.constants import SPLITS
from envs.config import config_from

#: Keys of the project section.
PROJECT_KEYS: Final[tuple[str, ...]] = (
    "algo",
    "env",
    "train_env",
    "val_env",
    "eval",
    "checkpoint_freq_steps",
    "keep_checkpoints",
    "vec_env",
    "pretrain",
    "action",
    "run",
)
#: Environment id whose config entry each forecast arm uses.
ENV_ID_OF: Final[dict[str, str]] = {
    "mesrnn": "CrowdNav-MESRNN-v0",
    "none": "CrowdNav-NoPred-v0",
    "cv": "CrowdNav-CV-v0",
    "oracle": "CrowdNav-Oracle-v0",
    "srnn": "CrowdNav-MESRNN-v0",
    "vlstm": "CrowdNav-MESRNN-v0",
    "noisy_oracle": "CrowdNav-MESRNN-v0",
}
#: Algorithms (``algo:``).
ALGOS: Final[tuple[str, ...]] = ("ppo", "sac")
#: RL Zoo keys of an entry that are not algorithm arguments.
ZOO_KEYS: Final[tuple[str, ...]] = ("n_envs", "n_timesteps", "policy", "policy_kwargs", "normalize")
#: The keyword arguments of SB3's PPO and SAC (2.x) an entry may set: their ``__init__`` parameters without those a
#: run sets itself (``policy``, ``env``, ``seed``, ``verbose``, ``device``, ``tensorboard_log``), ``policy_kwargs``
#: (one of :data:`ZOO_KEYS`) and the private ones (``_init_setup_model``). Written out so that a config is checked before SB3 (and torch) is imported;
#: ``tests/agents/training/test_config_keys.py`` keeps them equal to the installed SB3's.
ALGO_KEYS: Final[dict[str, tuple[str, ...]]] = {
    "ppo": (
        "learning_rate",
        "n_steps",
        "batch_size",
        "n_epochs",
        "gamma",
        "gae_lambda",
        "clip_range",
        "clip_range_vf",
        "normalize_advantage",
        "ent_coef",
        "vf_coef",
        "max_grad_norm",
        "use_sde",
        "sde_sample_freq",
        "rollout_buffer_class",
        "rollout_buffer_kwargs",
        "target_kl",
        "stats_window_size",
    ),
    "sac": (
        "learning_rate",
        "buffer_size",
        "learning_starts",
        "batch_size",
        "tau",
        "gamma",
        "train_freq",
        "gradient_steps",
        "action_noise",
        "replay_buffer_class",
        "replay_buffer_kwargs",
        "optimize_memory_usage",
        "n_steps",
        "ent_coef",
        "target_update_interval",
        "target_entropy",
        "use_sde",
        "sde_sample_freq",
        "use_sde_at_warmup",
        "stats_window_size",
    ),
}
#: RL Zoo keys this trainer does not implement (rejected with a message rather than ignored).
UNSUPPORTED_ZOO_KEYS: Final[tuple[str, ...]] = (
    "env_wrapper",
    "vec_env_wrapper",
    "frame_stack",
    "callback",
    "monitor_kwargs",
    "noise_type",
    "noise_std",
)
#: Environment settings a run sets itself (per run and per phase).
RUN_ENV_KEYS: Final[tuple[str, ...]] = ("predictor", "split", "part", "episode_time", "render_mode")
#: ``vec_env`` values (:attr:`TrainConfig.vec_env`); ``auto`` is the default.
VEC_ENVS: Final[tuple[str, ...]] = ("auto", "vector", "batched", "dummy", "subproc")
DEFAULT_CONFIG: Final[Path] = Path(__file__).resolve().parents[2] / "configs" / "agent" / "ppo.yaml"


@dataclass(frozen=True)
class EvalConfig:
    """The ``eval:`` section: periodic validation keeping ``best_model.zip``."""

    freq_steps: int = 25_000
    """Validate every this many environment steps (0: only at the end of training)."""
    episodes: int = 100
    """Validation episodes (0: no validation, no best model)."""
    seed: int = 1
    """Which seeded list of validation episodes (fixed for the whole run, the same in every arm)."""
    n_envs: int = 4
    """Validation environments stepped in lockstep in the main process (speed only)."""
    require_pedestrians: bool = True
    """Validate only on episodes with a pedestrian near the straight path (as the test evaluation does)."""


#: Losses of the action fit.
ACTION_LOSSES: Final[tuple[str, ...]] = ("mse", "nll")

#: ``pretrain.teacher_predictor`` values: None (the teacher plans with the observation's forecasts, the student's arm)
#: or ``oracle`` (with the true future, whatever the arm).
TEACHER_PREDICTORS: Final[tuple[str | None, ...]] = (None, "oracle")


@dataclass(frozen=True)
class PretrainConfig:
    """The ``pretrain:`` section of a training config (None there = no warm start)."""

    teacher: str = "planner"
    """A policy of :mod:`agents.planners` by name (:data:`agents.planners.PLANNERS`: ``planner``, the sampling
    planner; ``straight``; the search and privileged planners where that module offers them), or any class with
    SB3's batched ``predict`` as ``"package.module:Class"``, built as ``Class(env_config, **teacher_kwargs)``.
    A teacher with a ``bind_envs(envs)`` method (one that reads the environments, e.g. the privileged planner) is
    given the environment of each row before every batched ``predict`` (as :func:`agents.rollout.run_episodes`
    does) and asked for its action at every step, before the environments move on."""
    teacher_kwargs: dict[str, Any] = field(default_factory=dict)
    """Options of the teacher (e.g. ``headings_deg``, ``margin_m`` of the sampling planner)."""
    teacher_predictor: str | None = None
    """The forecasts the teacher plans with: None, the observation's (the student's arm); ``oracle``, the true future
    of the same pedestrians whatever the student's arm (:class:`agents.training.pretrain.TrueFutureTeacher`, a
    privileged teacher reading its environments): one teacher labels every arm's states, and the students differ only
    in their forecast input. Only for teachers that read forecasts (``planner``, ``search``, a class path)."""
    episodes: int = 200
    """Teacher episodes on the training environments (part ``train``, ``episode_time="train"``)."""
    n_envs: int = 4
    """Environments the teacher drives in lockstep in the main process (speed only)."""
    epochs: int = 10
    """Passes over the teacher's transitions."""
    batch_size: int = 256
    """Transitions per gradient step."""
    lr: float = 1e-3
    """Adam learning rate of the warm start (a fresh optimiser; the algorithm's own is untouched)."""
    loss: str = "mse"
    """Action loss: ``mse`` on the action mean or ``nll`` (Gaussian negative log-likelihood; PPO only)."""
    value: bool = True
    """Also fit the value function (PPO) or critics (SAC) to discounted Monte-Carlo returns (gamma of the algorithm)."""
    dagger_rounds: int = 0
    """DAgger (Ross et al. 2011) rounds after the first fit: the policy drives ``dagger_episodes`` new episodes,
    the teacher labels every observation it met, and the policy is refitted on everything gathered so far. Cloning
    alone only ever sees the teacher's states, and the student's first mistakes lead where it has no labels."""
    dagger_episodes: int | None = None
    """Episodes the policy drives per DAgger round (default: ``episodes``)."""
    dagger_epochs: int | None = None
    """Passes over the aggregated data per DAgger round (default: ``epochs``); the fit continues from the last one."""
    value_coef: float = 0.5
    """Weight of the value loss (Huber) against the action loss; PPO shares the extractor between both."""
    log_std: float | None = -1.0
    """PPO: set the action log standard deviation to this afterwards (None keeps it)."""

    def validate(self) -> PretrainConfig:
        teacher_class(self.teacher)  # a clear error now rather than after the environments are built
        if self.teacher_predictor not in TEACHER_PREDICTORS:
            raise ConfigError(
                f"pretrain key 'teacher_predictor' must be null (the student's arm's forecasts) or "
                f"{', '.join(repr(p) for p in TEACHER_PREDICTORS if p)}, got {self.teacher_predictor!r}"
            )
        if self.teacher_predictor is not None and self.teacher in ("straight", "privileged"):
            raise ConfigError(
                f"pretrain key 'teacher_predictor' ({self.teacher_predictor!r}) needs a teacher that plans with "
                f"forecasts (planner, search or a class path); the {self.teacher!r} teacher reads none"
            )
        if self.loss not in ACTION_LOSSES:
            raise ConfigError(f"unknown pretrain loss {self.loss!r}; valid: {', '.join(ACTION_LOSSES)}")
        for key in ("dagger_rounds", "dagger_episodes", "dagger_epochs"):
            value = getattr(self, key)
            if key != "dagger_rounds" and value is None:
                continue
            if not isinstance(value, int) or isinstance(value, bool) or value < (0 if key == "dagger_rounds" else 1):
                raise ConfigError(
                    f"pretrain key {key!r} must be a whole number >= {0 if key == 'dagger_rounds' else 1}, got {value!r}"
                )
        for key in ("episodes", "n_envs", "epochs", "batch_size"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < (0 if key == "episodes" else 1):
                raise ConfigError(f"pretrain key {key!r} must be a positive integer, got {value!r}")
        if not (isinstance(self.lr, int | float) and math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"pretrain key 'lr' must be a positive number, got {self.lr!r}")
        if not isinstance(self.teacher_kwargs, Mapping):
            raise ConfigError(f"pretrain key 'teacher_kwargs' must be a mapping, got {self.teacher_kwargs!r}")
        return self


def teacher_class(name: str) -> Any:
    """The teacher a ``pretrain.teacher`` value names: None for a planner of :mod:`agents.planners` (built by
    :func:`agents.planners.make_planner`), else the class of a ``"package.module:Class"`` path.

    Raises:
        ConfigError: an unknown name (listing the planners this version offers) or a path that does not import.
    """
    from crowdnav_mesrnn.config import ConfigError

    if not isinstance(name, str):
        raise ConfigError(f"pretrain key 'teacher' must be a planner name or 'package.module:Class', got {name!r}")
    if name in PLANNERS:
        return None
    module, sep, attr = name.partition(":")
    if not sep:
        raise ConfigError(
            f"pretrain teacher {name!r} is not a planner of agents.planners in this version (available: "
            f"{', '.join(PLANNERS)}; the search and privileged planners are named 'search' and 'privileged' where "
            "agents.planners offers them) nor a 'package.module:Class' path"
        )
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"pretrain teacher {name!r} cannot be imported: {exc}") from None
    if not callable(getattr(cls, "predict", None)):
        raise ConfigError(f"pretrain teacher {name!r} has no predict method (SB3's batched predict is needed)")
    return cls


@dataclass(frozen=True)
class TrainConfig:
    """A resolved training configuration (see the module docstring for the file layout)."""

    algo: str
    """``ppo`` or ``sac``."""
    env_id: str
    """The config entry used (RL Zoo's key)."""
    predictor: str
    """Forecast arm of the environments."""
    split: str
    """Leave-one-out split: training on its four training scenes, never its held-out scene."""
    seed: int
    """Seeds the algorithm, the environments and the warm start."""
    n_timesteps: int
    """Environment steps in total."""
    n_envs: int
    """Parallel training environments (subprocesses when >= 2, see ``vec_env``)."""
    policy: str
    """SB3 policy: an alias (``MultiInputPolicy``) or a dotted class path."""
    policy_kwargs: dict[str, Any]
    """Keyword arguments of the policy (plain data)."""
    normalize: bool | dict[str, Any]
    """``VecNormalize`` (False, True or its keyword arguments); the mask is never normalised."""
    hyperparams: dict[str, Any]
    """The algorithm's other keyword arguments, as written (schedules as ``lin_<x>`` strings)."""
    env: dict[str, Any]
    """Environment settings shared by training, validation and evaluation."""
    eval: EvalConfig
    checkpoint_freq_steps: int
    """Checkpoint every this many steps (0: never; an interrupted run then restarts)."""
    keep_checkpoints: int
    """How many checkpoints to keep (the latest ones)."""
    vec_env: str
    """How the training environments are stepped (all give the same transitions, step for step; only speed differs):
    ``vector``: the batched environment (:class:`envs.vector.BatchedCrowdNavEnv`, the ids' ``vector_entry_point``:
    every environment in one call) through :class:`agents.batched_vec_env.BatchedVecEnv`; refused with a
    :class:`ConfigError` naming why where it cannot run the settings (:func:`batched_env_refusal`). ``auto`` (the
    default): ``vector`` where it can, else, with a warning naming why, the former default (``subproc`` for 2+
    environments, ``dummy`` for one). ``dummy``: SB3's ``DummyVecEnv`` over wrapped single environments;
    ``subproc``: one forkserver worker per environment; ``batched``: :class:`agents.vec_env.CrowdVecEnv` (single
    environments in this process, the wrappers' work batched)."""
    pretrain: PretrainConfig | None
    """Behaviour-cloning warm start, or None."""
    action: dict[str, Any] = dataclasses.field(default_factory=lambda: {"kind": "continuous"})
    """The ``action:`` section: ``kind`` (``continuous``: the environment's velocity box; ``discrete``: the
    goal-relative velocities of :mod:`agents.actions`, PPO only) and the discrete set's options."""
    source: str = ""
    """The file it was read from."""
    train_env: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Environment settings of training episodes only (the warm start's too), on top of ``env``: e.g.
    ``crowd_overlays`` (denser training crowds from the training recordings). Validation and evaluation never get
    them."""
    val_env: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Environment settings of validation episodes only, on top of ``env``: e.g. ``crowd_overlays`` to validate on
    denser crowds made from the training scenes' validation period (never the held-out scene). Evaluation never
    gets them."""

    def env_kwargs(self, episode_time: str = "train") -> dict[str, Any]:
        """Keyword arguments of a training (``train``, with ``train_env``) or validation (``val``, with ``val_env``)
        environment."""
        return {
            **self.env,
            **(self.train_env if episode_time == "train" else self.val_env if episode_time == "val" else {}),
            "predictor": self.predictor,
            "split": self.split,
            "part": "train",
            "episode_time": episode_time,
        }

    def to_yaml(self) -> dict[str, Any]:
        """The config in the file layout (an entry for ``env_id`` and the project section)."""
        entry: dict[str, Any] = {
            "n_envs": self.n_envs,
            "n_timesteps": self.n_timesteps,
            "policy": self.policy,
            "normalize": copy.deepcopy(self.normalize),
            "policy_kwargs": copy.deepcopy(self.policy_kwargs),
            **copy.deepcopy(self.hyperparams),
        }
        project = {
            "algo": self.algo,
            "env": copy.deepcopy(self.env),
            "eval": dataclasses.asdict(self.eval),
            "checkpoint_freq_steps": self.checkpoint_freq_steps,
            "keep_checkpoints": self.keep_checkpoints,
            "vec_env": self.vec_env,
            "pretrain": None if self.pretrain is None else dataclasses.asdict(self.pretrain),
            "action": copy.deepcopy(self.action),
        }
        for key in ("train_env", "val_env"):  # written only when set (older run folders compare equal on resume)
            if getattr(self, key):
                project[key] = copy.deepcopy(getattr(self, key))
        return {self.env_id: entry, PROJECT_KEY: project}

    def action_set(self) -> Any:
        """The discrete action set (:class:`agents.actions.GoalRelativeActions`), or None for continuous actions."""
        return action_set(self.action, config_from(self.env_kwargs("train"), {}))


def env_id_for(predictor: str) -> str:
    """The config entry (environment id) of a forecast arm."""
    if predictor not in ENV_ID_OF:
        predictors.check(predictor)
        return ENV_ID_OF["mesrnn"]  # a plug-in: the learned arms' entry, with its own predictor
    return ENV_ID_OF[predictor]


def _set_dotted(target: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    node = target
    for part in parts[:-1]:
        if not isinstance(node.get(part), dict):
            node[part] = {}
        node = node[part]
    node[parts[-1]] = value


def _algo_class(algo: str) -> Any:
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


def _check_entry_keys(algo: str, entry: Mapping[str, Any], env_id: str, where: str) -> None:
    """Every key of an entry is an RL Zoo key (:data:`ZOO_KEYS`) or an argument of the algorithm
    (:data:`ALGO_KEYS`): a misspelt one is named with the closest valid key (``n_timestep``: did you mean
    ``n_timesteps``?), before anything heavy is imported."""
    check_keys(entry, [*ZOO_KEYS, *ALGO_KEYS[algo]], f"{algo} entry {env_id!r} ({where})")


def load_train_config(
    path: str | Path, env_id: str | None = None, overrides: Mapping[str, Any] | None = None
) -> TrainConfig:
    """Read a training config and apply overrides.

    Args:
        path: a YAML file in the layout of the module docstring (also a run folder's ``config.yaml``).
        env_id: the entry to use; default: the one of the predictor (``overrides["predictor"]``, else the
            run section's, else ``mesrnn``).
        overrides: ``predictor``, ``split``, ``seed`` (the run), and dotted keys: ``env.*``, ``eval.*``,
            ``pretrain.*`` and the other project keys go to the project section, everything else to the
            entry (``learning_rate``, ``n_envs``, ``policy_kwargs.net_arch``, ...). ``pretrain: null``
            disables the warm start; ``pretrain.<key>`` on a disabled one enables it with defaults.

    Raises:
        ConfigError: naming the key and listing the valid ones.
    """
    path = existing_config(path, "agent")
    raw = load_yaml(path)
    over = dict(overrides or {})
    project = copy.deepcopy(raw.get(PROJECT_KEY) or {})
    if not isinstance(project, dict):
        raise ConfigError(f"{path}: {PROJECT_KEY!r} must be a mapping")
    run = project.pop("run", None) or {}
    predictor = str(over.pop("predictor", None) or run.get("predictor") or "mesrnn")
    split = str(over.pop("split", None) or run.get("split") or "zara1")
    seed_value = over.pop("seed", None)
    seed = int(seed_value if seed_value is not None else run.get("seed", 0))
    predictors.check(predictor)
    if split not in SPLITS:
        raise ConfigError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    env_id = env_id or env_id_for(predictor)
    ids = [k for k in raw if k != PROJECT_KEY]
    if env_id not in raw or not isinstance(raw[env_id], dict):
        raise ConfigError(f"{path}: no entry for environment id {env_id!r}; entries: {', '.join(ids) or 'none'}")
    entry = copy.deepcopy(raw[env_id])
    for key, value in over.items():
        _set_dotted(project if key.split(".")[0] in PROJECT_KEYS else entry, key, value)
    check_keys(project, PROJECT_KEYS, f"{PROJECT_KEY} section of {path}")
    return _build(entry, project, env_id, predictor, split, seed, str(path))


def _build(
    entry: dict[str, Any], project: dict[str, Any], env_id: str, predictor: str, split: str, seed: int, source: str
) -> TrainConfig:
    algo = project.get("algo")
    if algo not in ALGOS:
        raise ConfigError(f"{source}: {PROJECT_KEY}.algo must be one of {', '.join(ALGOS)}, got {algo!r}")
    for key in UNSUPPORTED_ZOO_KEYS:
        if key in entry:
            raise ConfigError(f"{source}: RL Zoo key {key!r} is not supported by agents.train")
    _check_entry_keys(algo, entry, env_id, source)  # a misspelt key is named before a missing one is asked for
    for key in ("n_timesteps", "policy"):
        if key not in entry:
            raise ConfigError(f"{source}: entry {env_id!r} needs {key!r}")
    policy_kwargs = entry.pop("policy_kwargs", None) or {}
    if not isinstance(policy_kwargs, dict):
        raise ConfigError(
            f"{source}: policy_kwargs must be a YAML mapping (a string would need eval, which this project never does)"
        )
    normalize = entry.pop("normalize", False)
    if not isinstance(normalize, bool | dict):
        raise ConfigError(f"{source}: normalize must be true, false or a mapping of VecNormalize arguments")
    n_timesteps = _positive_int(entry.pop("n_timesteps"), "n_timesteps")
    n_envs = _positive_int(entry.pop("n_envs", 1), "n_envs")
    policy = entry.pop("policy")
    if not isinstance(policy, str):
        raise ConfigError(f"{source}: policy must be a name or a dotted class path, got {policy!r}")
    env = project.get("env") or {}
    if not isinstance(env, dict):
        raise ConfigError(f"{source}: {PROJECT_KEY}.env must be a mapping")
    train_env, val_env = project.get("train_env") or {}, project.get("val_env") or {}
    for section, values in (("train_env", train_env), ("val_env", val_env)):
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: {PROJECT_KEY}.{section} must be a mapping")
    for section, values in (("env", env), ("train_env", train_env), ("val_env", val_env)):
        for key in RUN_ENV_KEYS:
            if key in values:
                raise ConfigError(
                    f"{PROJECT_KEY}.{section}.{key} is set by the run (use --predictor/--split), not the config"
                )
    eval_section = project.get("eval") or {}
    eval_cfg = replace_checked(EvalConfig(), eval_section, where=f"{PROJECT_KEY}.eval")
    pre = project.get("pretrain")
    pretrain = None if pre is None else replace_checked(PretrainConfig(), pre, where="pretrain").validate()
    action = project.get("action") or {"kind": "continuous"}
    if not isinstance(action, dict):
        raise ConfigError(f"{source}: {PROJECT_KEY}.action must be a mapping with a 'kind'")
    action = {"kind": "continuous", **action}
    if action["kind"] == "discrete" and algo != "ppo":
        raise ConfigError(f"action kind 'discrete' needs algo 'ppo' (SAC acts in a continuous space), got {algo!r}")
    vec_env = project.get("vec_env", "auto")
    if vec_env not in VEC_ENVS:
        raise ConfigError(f"unknown vec_env {vec_env!r}; valid: {', '.join(VEC_ENVS)}")
    cfg = TrainConfig(
        algo=algo,
        env_id=env_id,
        predictor=predictor,
        split=split,
        seed=seed,
        n_timesteps=n_timesteps,
        n_envs=n_envs,
        policy=policy,
        policy_kwargs=policy_kwargs,
        normalize=normalize,
        hyperparams=entry,
        env=dict(env),
        eval=eval_cfg,
        checkpoint_freq_steps=_positive_int(project.get("checkpoint_freq_steps", 50_000), "checkpoint_freq_steps", 0),
        keep_checkpoints=_positive_int(project.get("keep_checkpoints", 1), "keep_checkpoints"),
        vec_env=vec_env,
        pretrain=pretrain,
        action=action,
        source=source,
        train_env=dict(train_env),
        val_env=dict(val_env),
    )
    config_from(cfg.env_kwargs("val"), {})  # a bad validation setting is named now, not at the first validation
    cfg.action_set()  # validates the environment settings and the action section now, naming the bad key
    if vec_env == "vector":
        why = batched_env_refusal(cfg)
        if why is not None:
            raise ConfigError(
                f"{source}: {PROJECT_KEY}.vec_env 'vector' cannot train these settings: {why}; set vec_env 'dummy' or "
                "'subproc' (single environments), or 'auto' (the batched environment where it can, else single "
                "environments with a warning)"
            )
    return cfg


def batched_env_refusal(cfg: TrainConfig) -> str | None:
    """Why the batched environment (``vec_env: vector``) cannot step a run's training environments, or None when it
    can: pedestrians that react to the robot (``env.reaction`` / ``train_env.reaction`` other than ``none``; the
    batched environment replays the recordings only) or more environments than it batches. Every other setting,
    the discrete actions and ``VecNormalize`` included, it runs as the single environments do."""
    reaction = config_from(cfg.env_kwargs("train"), {}).reaction
    if reaction != "none":
        return (
            f"env key 'reaction' = {reaction!r} (pedestrians reacting to the robot): the batched environment "
            "replays the recordings only (reaction 'none')"
        )
    from envs.vector.physics import MAX_WORLDS

    if cfg.n_envs > MAX_WORLDS:
        return f"n_envs = {cfg.n_envs}: the batched environment steps at most {MAX_WORLDS} environments"
    return None


def vec_env_kind(cfg: TrainConfig) -> tuple[str, str | None]:
    """The ``vec_env`` a run steps its training environments with (``auto`` resolved: :attr:`TrainConfig.vec_env`),
    and why ``auto`` fell back from ``vector`` (None when it did not)."""
    if cfg.vec_env != "auto":
        return cfg.vec_env, None
    why = batched_env_refusal(cfg)
    if why is None:
        return "vector", None
    return ("subproc" if cfg.n_envs >= 2 else "dummy"), why


def _positive_int(value: Any, key: str, minimum: int = 1) -> int:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be an integer >= {minimum}, got {value!r}") from None
    if isinstance(value, bool) or not x.is_integer() or x < minimum:
        raise ConfigError(f"{key} must be an integer >= {minimum}, got {value!r}")
    return int(x)


class LinearSchedule:
    """RL Zoo's ``lin_<initial>``: ``initial * progress_remaining`` (1 at the start, 0 at the end)."""

    def __init__(self, initial: float) -> None:
        self.initial = float(initial)

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.initial

    def __repr__(self) -> str:
        return f"lin_{self.initial}"


def _schedule(value: Any, key: str) -> Any:
    if isinstance(value, str):
        kind, _, initial = value.partition("_")
        if kind != "lin":
            raise ConfigError(f"{key}: schedules are written lin_<initial>, got {value!r}")
        try:
            return LinearSchedule(float(initial))
        except ValueError:
            raise ConfigError(f"{key}: schedules are written lin_<initial>, got {value!r}") from None
    return value


def algorithm_kwargs(cfg: TrainConfig) -> dict[str, Any]:
    """The algorithm's keyword arguments (schedules built, policy class imported)."""
    from agents.scoring import GeometryCachingBuffer, action_geometry_kwargs, is_scoring_policy

    kwargs = copy.deepcopy(cfg.hyperparams)
    for key in ("learning_rate", "clip_range", "clip_range_vf"):
        if key in kwargs:
            kwargs[key] = _schedule(kwargs[key], key)
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    kwargs["policy_kwargs"] = copy.deepcopy(cfg.policy_kwargs)
    if is_scoring_policy(policy_class(cfg.policy)):  # the scoring policy rolls out the action set's velocities
        actions = cfg.action_set()
        if actions is None:
            raise ConfigError(f"policy {cfg.policy} scores discrete actions: set action kind 'discrete'")
        if cfg.algo == "ppo":  # the geometry depends on the observation alone: computed once per rollout
            kwargs.setdefault("rollout_buffer_class", GeometryCachingBuffer)
        extractor = kwargs["policy_kwargs"].setdefault("features_extractor_kwargs", {})
        for key, value in action_geometry_kwargs(actions).items():
            if extractor.setdefault(key, value) != value:
                raise ConfigError(
                    f"policy_kwargs.features_extractor_kwargs.{key} = {extractor[key]!r} disagrees with the action set "
                    f"and environment ({value!r}); leave it out, it is filled in from them"
                )
    return kwargs


def policy_class(name: str) -> Any:
    """An SB3 policy alias (returned as is) or the class named by a dotted path."""
    if "." not in name:
        return name
    module, _, cls = name.rpartition(".")
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"policy {name!r} cannot be imported: {exc}") from None
