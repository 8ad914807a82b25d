"""Train a navigation policy (PPO or SAC) on ``CrowdNav-*`` from a YAML config; every run is a folder.

``python -m agents.train --config configs/agent/ppo.yaml --predictor mesrnn --split zara1 --seed 0
[--timesteps N] [--out RUN_DIR] [--resume] [--set key=value ...]`` (also ``crowdnav-mesrnn agent train``).

## Config files
RL Zoo's layout: one top-level entry per environment id holding the algorithm's hyperparameters
(``n_envs``, ``n_timesteps``, ``policy``, ``policy_kwargs``, ``normalize`` and the algorithm's own
keyword arguments), so the same file works with ``python -m rl_zoo3.train --algo ppo --env
CrowdNav-MESRNN-v0 --gym-packages crowdnav_mesrnn -conf configs/agent/ppo.yaml``. Settings of this
project live under the separate top-level key ``crowdnav_mesrnn`` (RL Zoo reads only the entry of
the environment id it trains): ``algo``, ``env`` (environment settings, e.g. reward weights,
``time_penalty``, ``observe_time_left``), ``eval``, ``checkpoint_freq_steps``, ``keep_checkpoints``,
``vec_env``, ``pretrain`` (behaviour-cloning warm start, :mod:`agents.pretrain`) and ``action``
(``kind: continuous``, or ``discrete`` for the goal-relative velocities of :mod:`agents.actions`, PPO only). Everything is read
with ``yaml.safe_load``; nothing is evaluated: ``policy_kwargs`` is a mapping (activation functions by
name, see :mod:`agents.extractors`), learning-rate schedules are RL Zoo's ``lin_<initial>`` strings.

The forecast arm chooses the entry: ``mesrnn`` -> ``CrowdNav-MESRNN-v0``, ``none`` -> ``CrowdNav-NoPred-v0``,
``cv`` -> ``CrowdNav-CV-v0``, ``oracle`` -> ``CrowdNav-Oracle-v0``; ``srnn``, ``vlstm`` and
``noisy_oracle`` use the ``CrowdNav-MESRNN-v0`` entry with their own predictor.

## Episodes
Training episodes replay the split's four training scenes (``part="train"``) in the first
``1 - val_fraction`` of each recording (``episode_time="train"``); validation episodes replay the same
scenes' last ``val_fraction`` (``episode_time="val"``) — never the held-out test scene.

## A run folder
``config.yaml`` (the resolved config in the same layout, plus a ``run`` section: predictor, split, seed,
environment id, the resolved environment settings, the crowd replayed (``crowd``: ``kind`` and ETH/UCY
``data_dir``), sha256 of the predictor weights involved, code version), ``command.txt``, ``version.txt``, ``progress.csv`` (SB3's logger), ``evaluations.csv``
(validation history), ``best_model.zip`` (best validation success rate, ties broken by return),
``final_model.zip`` (``*_vecnormalize.pkl`` beside the models when observations are normalised),
``pretrain.json`` (warm start), ``checkpoints/`` (model, ``VecNormalize`` statistics, SAC's replay
buffer and the validation state every ``checkpoint_freq_steps``; ``--resume`` continues from the
latest with the same timestep count), ``tb/`` (TensorBoard, when installed) and ``DONE``, written last.
Every file is written atomically.
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import hashlib
import importlib
import importlib.util
import inspect
import io
import json
import pickle
import shlex
import shutil
import sys
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any, Final

import numpy as np
import yaml
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import KVWriter, Logger, TensorBoardOutputFormat, filter_excluded_keys

from agents.evaluate import SB3Policy, evaluation_seeds, parse_set, prepare_forecasts, run_episodes
from agents.pretrain import PretrainConfig
from agents.scoring import GeometryCachingBuffer, action_geometry_kwargs, attach_geometry_cache, is_scoring_policy
from agents.stats import wilson_interval
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, check_keys, load_yaml, replace_checked
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text, code_version
from envs.config import config_from, crowd_source, episode_recordings

#: Top-level key of the project's own settings in a config file (RL Zoo ignores it).
PROJECT_KEY: Final[str] = "crowdnav_mesrnn"
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
VEC_ENVS: Final[tuple[str, ...]] = ("auto", "subproc", "dummy", "batched")
DEFAULT_CONFIG: Final[Path] = Path(__file__).resolve().parent.parent / "configs" / "agent" / "ppo.yaml"


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
    """``auto`` (subprocesses for 2+ environments), ``subproc``, ``dummy`` (SB3's ``DummyVecEnv`` over wrapped
    environments) or ``batched`` (:class:`agents.vec_env.CrowdVecEnv`: the same in this process, the wrappers' work
    batched)."""
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


# ---------------------------------------------------------------------------- loading configs


def action_set(action: Mapping[str, Any] | None, env_config: Any) -> Any:
    """The discrete action set an ``action:`` section describes for an environment configuration, or None."""
    from agents.actions import ACTION_KINDS, make_actions

    options = dict(action or {})
    kind = options.pop("kind", "continuous")
    if kind not in ACTION_KINDS:
        raise ConfigError(f"unknown action kind {kind!r}; valid: {', '.join(ACTION_KINDS)}")
    if kind == "continuous":
        if options:
            raise ConfigError(f"action kind 'continuous' takes no options, got {', '.join(sorted(options))}")
        return None
    return make_actions(env_config, options)


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
    return {"ppo": PPO, "sac": SAC}[algo]


def _check_hyperparams(algo: str, hyperparams: Mapping[str, Any], where: str) -> None:
    params = inspect.signature(_algo_class(algo).__init__).parameters
    valid = [p for p in params if p not in ("self", "policy", "env", "seed", "verbose", "device", "tensorboard_log")]
    check_keys(hyperparams, valid, f"{algo} hyperparameter ({where})")


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
    path = Path(path)
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
    _check_hyperparams(algo, entry, source)
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
    return cfg


def _positive_int(value: Any, key: str, minimum: int = 1) -> int:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be an integer >= {minimum}, got {value!r}") from None
    if isinstance(value, bool) or not x.is_integer() or x < minimum:
        raise ConfigError(f"{key} must be an integer >= {minimum}, got {value!r}")
    return int(x)


# ---------------------------------------------------------------------------- building the algorithm


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


def make_env(env_kwargs: Mapping[str, Any], action: Mapping[str, Any] | None = None) -> Any:
    """A training environment (run in the worker process): one torch thread, the discrete action wrapper when
    ``action`` says so, SB3's ``Monitor``, and ``info["is_success"]`` at the end of an episode (SB3 logs it as
    ``rollout/success_rate``)."""
    import gymnasium as gym
    import torch
    from stable_baselines3.common.monitor import Monitor

    from envs.crowd_nav import CrowdNavEnv

    torch.set_num_threads(1)

    class SuccessInfo(gym.Wrapper):
        def step(self, action: Any) -> Any:
            obs, reward, terminated, truncated, info = self.env.step(action)
            if terminated or truncated:
                info["is_success"] = info["episode_metrics"]["outcome"] == "success"
            return obs, reward, terminated, truncated, info

    env: gym.Env = CrowdNavEnv(**dict(env_kwargs))
    actions = action_set(action, env.unwrapped.config)
    if actions is not None:
        from agents.actions import DiscreteActionWrapper

        env = DiscreteActionWrapper(env, actions)
    return Monitor(SuccessInfo(env))


def make_vec_env(cfg: TrainConfig) -> Any:
    """The training ``VecEnv`` (``SubprocVecEnv`` with the forkserver start method for 2+ environments under
    ``vec_env: auto``), wrapped in ``VecNormalize`` when configured."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    if cfg.vec_env == "batched":
        from agents.vec_env import CrowdVecEnv
        from envs.crowd_nav import CrowdNavEnv

        bare = [partial(CrowdNavEnv, **cfg.env_kwargs("train")) for _ in range(cfg.n_envs)]
        venv: Any = CrowdVecEnv(bare, cfg.action_set())
    else:
        fns = [partial(make_env, cfg.env_kwargs("train"), cfg.action) for _ in range(cfg.n_envs)]
        subproc = cfg.vec_env == "subproc" or (cfg.vec_env == "auto" and cfg.n_envs >= 2)
        venv = SubprocVecEnv(fns, start_method="forkserver") if subproc else DummyVecEnv(fns)
    if cfg.normalize:
        from gymnasium import spaces
        from stable_baselines3.common.vec_env import VecNormalize

        nkw = dict(cfg.normalize) if isinstance(cfg.normalize, dict) else {}
        nkw.setdefault(
            "norm_obs_keys", [k for k, s in venv.observation_space.spaces.items() if isinstance(s, spaces.Box)]
        )
        nkw.setdefault("gamma", cfg.hyperparams.get("gamma", 0.99))
        venv = VecNormalize(venv, **nkw)
    return venv


def prepare_training_forecasts(cfg: TrainConfig, progress: bool = False) -> None:
    """Fill the shared forecast cache for the run's training and validation episodes (the same recordings), and for
    the overlaid recordings when ``train_env`` or ``val_env`` densifies them (``crowd_overlays``: their forecasts
    differ from the recordings' own and are computed here, once, rather than by the first environment needing them)."""
    prepare_forecasts(cfg.env_kwargs("train"), progress=progress)
    for phase in ("train", "val"):
        kwargs = cfg.env_kwargs(phase)
        if config_from(kwargs, {}).crowd_overlays:
            from envs.crowd_nav import CrowdNavEnv

            env = CrowdNavEnv(**kwargs)
            try:
                env.precompute_forecasts()
            finally:
                env.close()


def predictor_weights(cfg: TrainConfig) -> dict[str, str]:
    """sha256 of every pretrained predictor file the run's forecasts come from (training recordings)."""
    if cfg.predictor not in predictors.names(predictors.PRETRAINED, plugins=False):
        return {}
    from crowdnav_mesrnn.models.pretrained import pretrained_path
    from envs.forecasting.sources import split_of_recording

    out: dict[str, str] = {}
    for rec in episode_recordings(cfg.split, "train"):
        split = split_of_recording(rec)
        if split is None:
            continue
        path = pretrained_path(cfg.predictor, split)
        if path.is_file() and path.name not in out:
            out[path.name] = hashlib.sha256(path.read_bytes()).hexdigest()
    return dict(sorted(out.items()))


# ---------------------------------------------------------------------------- run-folder files


def _save_model(model: Any, path: Path) -> None:
    atomic_write(path, lambda fh: model.save(fh))


def _save_pickle(obj: Any, path: Path) -> None:
    atomic_write(path, lambda fh: pickle.dump(obj, fh))


def _save_vecnormalize(model: Any, model_file: Path) -> None:
    vn = model.get_vec_normalize_env()
    if vn is not None:
        venv, vn.venv = vn.venv, None  # the statistics only: worker processes cannot be pickled
        try:
            _save_pickle(vn, model_file.with_name(f"{model_file.stem}_vecnormalize.pkl"))
        finally:
            vn.venv = venv


def _csv_text(keys: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(keys), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, Any]]]:
    if not path.is_file():
        return [], []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or []), list(reader)


def _steps_of(row: Mapping[str, Any], key: str) -> float:
    try:
        return float(row.get(key) or 0)
    except ValueError:
        return 0.0


class ProgressCSV(KVWriter):
    """SB3 logger output writing ``progress.csv`` atomically (the whole file each time, new keys as new
    columns); on resume it keeps the rows logged up to the checkpoint."""

    def __init__(self, path: Path, keep_until_step: int | None = None) -> None:
        self.path = path
        self.keys, rows = _read_csv(path)
        if keep_until_step is None:
            rows = []
            self.keys = []
        self.rows = [r for r in rows if _steps_of(r, "time/total_timesteps") <= (keep_until_step or 0)]

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        values = filter_excluded_keys(key_values, key_excluded, "csv")
        row = {k: v for k, v in values.items() if isinstance(v, int | float | str | np.number)}
        self.keys.extend(k for k in row if k not in self.keys)
        self.rows.append(row)
        atomic_write_text(self.path, _csv_text(self.keys, self.rows))

    def close(self) -> None:
        pass


#: The note that TensorBoard logs are not written was shown in this process (it is shown once).
_TB_NOTICE_SHOWN = False


def make_logger(run_dir: Path, keep_until_step: int | None) -> Any:
    """SB3 logger: ``progress.csv`` and, when tensorboard is installed, TensorBoard under ``tb/`` (without it, one
    warning per process says the logs are not written and how to get them)."""
    global _TB_NOTICE_SHOWN
    formats: list[Any] = [ProgressCSV(run_dir / "progress.csv", keep_until_step)]
    if importlib.util.find_spec("tensorboard") is not None:
        formats.append(TensorBoardOutputFormat(str(run_dir / "tb")))
    elif not _TB_NOTICE_SHOWN:
        _TB_NOTICE_SHOWN = True
        warnings.warn(
            "TensorBoard logs (tb/ in the run folder) are not written: tensorboard is not installed; "
            "pip install 'crowdnav-mesrnn[tb]' to get them (progress.csv is written either way)",
            UserWarning,
            stacklevel=2,
        )
    return Logger(str(run_dir), formats)


# ---------------------------------------------------------------------------- callbacks


class Validation(BaseCallback):
    """Validate every ``freq_steps`` (and at the end); keep ``best_model.zip`` by success rate, then return."""

    def __init__(self, cfg: TrainConfig, run_dir: Path) -> None:
        super().__init__()
        self.cfg = cfg
        self.run_dir = run_dir
        self.envs: list[Any] = []
        self.seeds = evaluation_seeds(cfg.split, cfg.eval.episodes, cfg.eval.seed)
        self.actions = cfg.action_set()
        self.state: dict[str, Any] = {"best": None, "last_eval_step": 0, "history": []}

    @property
    def enabled(self) -> bool:
        return self.cfg.eval.episodes > 0

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # at a rollout's start the policy holds every update so far (SB3 trains between rollouts)
        freq = self.cfg.eval.freq_steps
        steps = int(self.model.num_timesteps)
        if self.enabled and freq > 0 and steps - self.state["last_eval_step"] >= freq:
            self.num_timesteps = steps
            self.validate()

    def finish(self) -> None:
        """Validate the final policy unless it was just validated."""
        self.num_timesteps = int(self.model.num_timesteps)
        if self.enabled and (not self.state["history"] or self.state["last_eval_step"] != self.num_timesteps):
            self.validate()
            self.logger.dump(self.num_timesteps)

    def validate(self) -> dict[str, Any]:
        from envs.crowd_nav import CrowdNavEnv

        started = time.perf_counter()
        if not self.envs:
            kwargs = {**self.cfg.env_kwargs("val"), "require_pedestrians": self.cfg.eval.require_pedestrians}
            self.envs = [CrowdNavEnv(**kwargs) for _ in range(max(1, min(self.cfg.eval.n_envs, len(self.seeds))))]
        policy: Any = SB3Policy(self.model, self.model.get_vec_normalize_env())
        if self.actions is not None:
            from agents.actions import DiscretePolicy

            policy = DiscretePolicy(policy, self.actions)
        rows = run_episodes(policy, self.envs, self.seeds)
        n = len(rows)
        successes = sum(r["outcome"] == "success" for r in rows)
        lo, hi = wilson_interval(successes, n)
        result = {
            "step": int(self.num_timesteps),
            "episodes": n,
            "success_rate": successes / n,
            "success_lo": lo,
            "success_hi": hi,
            "collision_rate": sum(r["outcome"] == "collision" for r in rows) / n,
            "timeout_rate": sum(r["outcome"] == "timeout" for r in rows) / n,
            "mean_return": float(np.mean([r["return"] for r in rows])),
            "seconds": round(time.perf_counter() - started, 3),
        }
        best = self.state["best"]
        result["new_best"] = best is None or (result["success_rate"], result["mean_return"]) > (
            best["success_rate"],
            best["mean_return"],
        )
        if result["new_best"]:
            self.state["best"] = result
            _save_model(self.model, self.run_dir / "best_model.zip")
            _save_vecnormalize(self.model, self.run_dir / "best_model.zip")
        self.state["history"].append(result)
        self.state["last_eval_step"] = int(self.num_timesteps)
        atomic_write_text(self.run_dir / "evaluations.csv", _csv_text(list(result), self.state["history"]))
        for key in ("success_rate", "collision_rate", "timeout_rate", "mean_return"):
            self.logger.record(f"eval/{key}", result[key])
        self.logger.record("eval/best_success_rate", self.state["best"]["success_rate"])
        self.logger.record("time/total_timesteps", int(self.num_timesteps))
        return result

    def close(self) -> None:
        for env in self.envs:
            env.close()
        self.envs = []


class Checkpoint(BaseCallback):
    """Save a checkpoint every ``freq_steps``, always at a round boundary (before a rollout is collected)."""

    def __init__(self, run_dir: Path, freq_steps: int, keep: int, validation: Any, last_step: int) -> None:
        super().__init__()
        self.run_dir, self.freq, self.keep, self.validation = run_dir, freq_steps, keep, validation
        self.last_step = last_step
        self.round_start: int | None = None
        """Steps when the rollout being collected began; None outside a rollout (during the update)."""
        self._normalization: Any = None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # between rollouts the model is consistent (no half-collected rollout is lost on resume)
        if self.freq > 0 and self.model.num_timesteps - self.last_step >= self.freq:
            self.save()
        self.round_start = int(self.model.num_timesteps)
        vec_normalize = self.model.get_vec_normalize_env()
        if vec_normalize is not None:  # its statistics move with every step of the rollout
            self._normalization = copy.deepcopy((vec_normalize.obs_rms, vec_normalize.ret_rms))

    def _on_rollout_end(self) -> None:
        self.round_start = None

    def save(self) -> Path:
        self.last_step = int(self.model.num_timesteps)
        return save_checkpoint(self.model, self.run_dir, self.validation.state, self.keep)

    def save_interrupted(self) -> int | None:
        """On an interrupt: a checkpoint of the last round boundary, so a resumed run ends at exactly its
        budget (rollouts are whole rounds). Interrupted while collecting a rollout, the weights are still
        those of the round's start: the step count and normalisation statistics go back there and the partial
        rollout is dropped. Interrupted during the update (weights half changed) or before the first rollout,
        nothing is saved (the last periodic checkpoint stands). Returns the steps saved, or None."""
        if self.round_start is None or self.round_start <= self.last_step:
            return None
        self.model.num_timesteps = self.round_start
        vec_normalize = self.model.get_vec_normalize_env()
        if vec_normalize is not None and self._normalization is not None:
            vec_normalize.obs_rms, vec_normalize.ret_rms = self._normalization
        self.save()
        return self.round_start


class Progress(BaseCallback):
    """A progress bar over the run's total steps (resumed runs start where they stopped)."""

    def __init__(self, total: int, validation: Any) -> None:
        super().__init__()
        self.total, self.validation, self.bar = total, validation, None

    def _on_training_start(self) -> None:
        from tqdm.auto import tqdm

        self.bar = tqdm(
            total=self.total,
            initial=self.model.num_timesteps,
            desc=f"{type(self.model).__name__} training",
            unit="step",
            dynamic_ncols=True,
        )

    def _on_step(self) -> bool:
        assert self.bar is not None
        self.bar.update(self.model.num_timesteps - self.bar.n)
        best = self.validation.state["best"]
        if best is not None and self.n_calls % 100 == 0:
            self.bar.set_postfix(best_val_success=f"{best['success_rate']:.2f}", refresh=False)
        return True

    def _on_training_end(self) -> None:
        if self.bar is not None:
            self.bar.close()


def save_checkpoint(model: Any, run_dir: Path, validation_state: Mapping[str, Any], keep: int = 1) -> Path:
    """``checkpoints/step_<n>/`` with ``model.zip``, ``model_vecnormalize.pkl``, ``replay_buffer.pkl`` (off-policy)
    and ``state.json``; then ``checkpoints/latest.json`` points at it; older ones beyond ``keep`` are removed."""
    steps = int(model.num_timesteps)
    root = run_dir / "checkpoints"
    folder = root / f"step_{steps:010d}"
    _save_model(model, folder / "model.zip")
    _save_vecnormalize(model, folder / "model.zip")
    if getattr(model, "replay_buffer", None) is not None:
        atomic_write(folder / "replay_buffer.pkl", lambda fh: model.save_replay_buffer(fh))
    atomic_write_json(folder / "state.json", {"steps": steps, "validation": validation_state})
    atomic_write_json(root / "latest.json", {"steps": steps, "folder": folder.name})
    for old in sorted(p for p in root.glob("step_*") if p.is_dir())[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return folder


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The folder ``checkpoints/latest.json`` points at, or None."""
    pointer = run_dir / "checkpoints" / "latest.json"
    if not pointer.is_file():
        return None
    folder = run_dir / "checkpoints" / json.loads(pointer.read_text())["folder"]
    return folder if (folder / "model.zip").is_file() else None


# ---------------------------------------------------------------------------- train


def rollout_steps(cfg: TrainConfig) -> tuple[int, str] | None:
    """Environment steps SB3 collects between two checks of the budget, and how they come about: PPO collects
    whole rollouts of ``n_steps x n_envs``; SAC ``train_freq`` (in steps) x ``n_envs``. None when it is not a fixed
    number (SAC's ``train_freq`` counted in episodes)."""
    if cfg.algo == "ppo":
        n_steps = int(cfg.hyperparams.get("n_steps", 2048))
        return n_steps * cfg.n_envs, f"PPO collects whole rollouts of n_steps {n_steps} x n_envs {cfg.n_envs}"
    freq = cfg.hyperparams.get("train_freq", 1)
    if isinstance(freq, list | tuple):
        if len(freq) == 2 and freq[1] == "episode":
            return None
        freq = freq[0]
    return int(freq) * cfg.n_envs, f"SAC collects train_freq {int(freq)} x n_envs {cfg.n_envs}"


def steps_trained(cfg: TrainConfig, start_step: int = 0) -> int | None:
    """How many environment steps a run of ``cfg`` from ``start_step`` ends at: SB3 checks the budget
    (``n_timesteps``) only between collections (:func:`rollout_steps`), so it rounds up to whole collections
    (PPO's ``n_steps 256 x n_envs 8``: ``--timesteps 256`` trains 2,048 steps). None when it is not fixed."""
    unit = rollout_steps(cfg)
    if unit is None or cfg.n_timesteps <= start_step:
        return None if unit is None else start_step
    return start_step + -(-(cfg.n_timesteps - start_step) // unit[0]) * unit[0]


def default_run_dir(cfg: TrainConfig) -> Path:
    """``runs/<algo>_<predictor>_<split>_s<seed>_<UTC time>``."""
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.algo}_{cfg.predictor}_{cfg.split}_s{cfg.seed}_{stamp}"


def _config_differences(a: Mapping[str, Any], b: Mapping[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out.extend(_config_differences(va, vb, f"{prefix}{key}."))
        elif va != vb:
            out.append(f"{prefix}{key}")
    return out


def resolved_yaml(cfg: TrainConfig, extra_run: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """What ``config.yaml`` holds: :meth:`TrainConfig.to_yaml` plus the ``run`` section (with ``crowd``, the crowd the
    environments replay: ``{"kind": "replay", "data_dir": ...}`` or ``{"kind": "synthetic", ...}``).

    Raises:
        DataNotFoundError: the run replays ETH/UCY scenes (``env.crowd`` ``auto`` or ``replay``) and the data is not
            found.
    """
    doc = cfg.to_yaml()
    env_cfg = config_from(cfg.env_kwargs("train"), {})
    env_resolved = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(env_cfg).items()}
    doc[PROJECT_KEY]["run"] = {
        "predictor": cfg.predictor,
        "split": cfg.split,
        "seed": cfg.seed,
        "env_id": cfg.env_id,
        "source": cfg.source,
        "env_resolved": env_resolved,
        "crowd": crowd_source(env_cfg, scene_named=True).as_dict(),
        "predictor_weights_sha256": predictor_weights(cfg),
        "code_version": code_version(),
        **dict(extra_run or {}),
    }
    return doc


def _check_resume_config(cfg: TrainConfig, run_dir: Path) -> None:
    saved = load_yaml(run_dir / "config.yaml")
    saved[PROJECT_KEY].pop("run", None)
    now = cfg.to_yaml()
    diff = [d for d in _config_differences(saved, now) if not d.endswith("n_timesteps")]
    if diff:
        raise ConfigError(
            f"--resume with another config than {run_dir / 'config.yaml'} (differs in {', '.join(diff)}); "
            "resume with that file (the default) or start a new run"
        )


def train(
    cfg: TrainConfig,
    out_dir: str | Path | None = None,
    resume: bool = False,
    progress: bool = True,
    command: str | None = None,
) -> Path:
    """Train a policy; returns the run folder (see the module docstring for what it holds).

    Args:
        cfg: the configuration (:func:`load_train_config`).
        out_dir: the run folder (default: :func:`default_run_dir`). Must be new or empty unless ``resume``.
        resume: continue from the latest checkpoint of ``out_dir`` (same timestep count); a finished run
            (``DONE``) is left as is; without a checkpoint the run starts over.
        progress: show a progress bar.
        command: the command line to record (default: ``sys.argv``).
    """
    import torch

    torch.set_num_threads(1)
    run_dir = Path(out_dir) if out_dir is not None else default_run_dir(cfg)
    if (run_dir / "DONE").is_file():
        if not resume:
            raise ConfigError(
                f"{run_dir} holds a finished run; choose another --out (or --resume with more --timesteps)"
            )
        done_steps = int(json.loads((run_dir / "DONE").read_text())["steps"])
        if cfg.n_timesteps <= done_steps:
            print(f"{run_dir} is finished ({done_steps} steps); nothing to resume")
            return run_dir
        (run_dir / "DONE").unlink()  # extending a finished run: it is unfinished until the new DONE
    ckpt = latest_checkpoint(run_dir) if resume else None
    if not resume and run_dir.exists() and any(run_dir.iterdir()):
        raise ConfigError(f"{run_dir} exists and is not empty; pass --resume to continue it, or choose another --out")
    if ckpt is not None and (run_dir / "config.yaml").is_file():
        _check_resume_config(cfg, run_dir)
    resolved = resolved_yaml(cfg)  # finds the data (or fails naming where it looked) before the folder is made
    run_dir.mkdir(parents=True, exist_ok=True)

    line = command if command is not None else shlex.join(sys.argv)
    if ckpt is None:
        atomic_write_text(run_dir / "command.txt", line + "\n")
    else:
        previous = (run_dir / "command.txt").read_text() if (run_dir / "command.txt").is_file() else ""
        atomic_write_text(run_dir / "command.txt", previous + f"# resumed from {ckpt.name}\n{line}\n")
    atomic_write_text(run_dir / "version.txt", code_version() + "\n")
    atomic_write_text(run_dir / "config.yaml", yaml.safe_dump(resolved, sort_keys=False))

    started = time.perf_counter()
    prepare_training_forecasts(cfg, progress)
    venv = make_vec_env(cfg)
    validation = Validation(cfg, run_dir)
    algo_cls = _algo_class(cfg.algo)
    try:
        if ckpt is None:
            model = algo_cls(
                policy_class(cfg.policy), venv, seed=cfg.seed, verbose=0, device="cpu", **algorithm_kwargs(cfg)
            )
            model.set_logger(make_logger(run_dir, None))
            attach_geometry_cache(model)
            if cfg.pretrain is not None and cfg.pretrain.episodes > 0:
                from agents.pretrain import pretrain

                gamma = float(cfg.hyperparams.get("gamma", 0.99))
                stats = pretrain(
                    model,
                    cfg.pretrain,
                    cfg.env_kwargs("train"),
                    cfg.seed,
                    gamma,
                    model.get_vec_normalize_env(),
                    progress,
                    actions=cfg.action_set(),
                )
                atomic_write_json(run_dir / "pretrain.json", stats)
                for key, value in stats.items():
                    if isinstance(value, int | float):
                        model.logger.record(f"pretrain/{key}", value)
                if validation.enabled:  # what the warm start alone achieves (and the best model until RL beats it)
                    validation.init_callback(model)
                    validation.num_timesteps = 0
                    validation.validate()
                    model.logger.dump(0)
            start_step = 0
        else:
            model = _resume_model(cfg, ckpt, venv, validation)
            start_step = int(model.num_timesteps)
            model.set_logger(make_logger(run_dir, start_step))
            print(f"resuming {run_dir} at step {start_step} of {cfg.n_timesteps}")
        planned = steps_trained(cfg, start_step)
        if planned is not None and planned != max(cfg.n_timesteps, start_step):
            unit = rollout_steps(cfg)
            assert unit is not None
            warnings.warn(
                f"n_timesteps {cfg.n_timesteps} trains {planned} steps: {unit[1]} = {unit[0]} steps at a time"
                + (f" (from step {start_step})" if start_step else "")
                + "; set a multiple of it to train exactly the budget",
                UserWarning,
                stacklevel=2,
            )
        checkpoint = Checkpoint(run_dir, cfg.checkpoint_freq_steps, cfg.keep_checkpoints, validation, start_step)
        callbacks = [validation, checkpoint] + ([Progress(cfg.n_timesteps, validation)] if progress else [])
        remaining = cfg.n_timesteps - start_step
        try:
            if remaining > 0:
                model.learn(remaining, callback=callbacks, reset_num_timesteps=False, progress_bar=False)
        except KeyboardInterrupt:
            saved = checkpoint.save_interrupted() if cfg.checkpoint_freq_steps > 0 else None
            last = latest_checkpoint(run_dir)
            where = (
                f"checkpoint at step {saved}"
                if saved is not None
                else f"last checkpoint: {last.name if last else 'none'}"
            )
            print(f"\ninterrupted at step {model.num_timesteps}: {where} (a round boundary); continue with --resume")
            raise
        validation.init_callback(model)
        validation.finish()
        _save_model(model, run_dir / "final_model.zip")
        _save_vecnormalize(model, run_dir / "final_model.zip")
        if cfg.checkpoint_freq_steps > 0 and checkpoint.last_step != model.num_timesteps:
            checkpoint.save()
        validation.close()
    finally:
        venv.close()
    done = {
        "steps": int(model.num_timesteps),
        "seconds_this_session": round(time.perf_counter() - started, 1),
        "best_validation": validation.state["best"],
        "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    atomic_write_json(run_dir / "DONE", done)
    return run_dir


def _resume_model(cfg: TrainConfig, ckpt: Path, venv: Any, validation: Any) -> Any:
    """Load the checkpoint's model (with the live ``venv``), normalisation statistics, replay buffer and
    validation state; reseed with ``seed + steps`` so the resumed run meets new episodes."""
    algo_cls = _algo_class(cfg.algo)
    stats_file = ckpt / "model_vecnormalize.pkl"
    if stats_file.is_file():
        from stable_baselines3.common.vec_env import VecNormalize

        with open(stats_file, "rb") as fh:
            saved = pickle.load(fh)
        if not isinstance(venv, VecNormalize):
            raise ConfigError(f"{ckpt} has VecNormalize statistics but the config does not normalise")
        venv.obs_rms, venv.ret_rms = saved.obs_rms, saved.ret_rms
    model = algo_cls.load(ckpt / "model.zip", env=venv, device="cpu")
    attach_geometry_cache(model)
    if (ckpt / "replay_buffer.pkl").is_file() and hasattr(model, "load_replay_buffer"):
        model.load_replay_buffer(ckpt / "replay_buffer.pkl")
    state = json.loads((ckpt / "state.json").read_text())
    validation.state = state["validation"]
    model.set_random_seed(cfg.seed + int(model.num_timesteps))
    return model


# ---------------------------------------------------------------------------- command line


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        default=None,
        help="training YAML (default: configs/agent/ppo.yaml; with --resume: the run's config.yaml)",
    )
    p.add_argument(
        "--predictor",
        default=None,
        metavar="PREDICTOR",
        help=f"forecast arm: {', '.join(predictors.names(plugins=False))}, an installed predictor plug-in or an "
        "import path package.module:Factory (default: mesrnn)",
    )
    p.add_argument("--split", default=None, choices=SPLITS, help="train on its four training scenes (default: zara1)")
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--seed", type=int, default=None, help="seed (default: 0)")
    p.add_argument("--timesteps", type=float, default=None, help="total environment steps (overrides n_timesteps)")
    p.add_argument("--out", default=None, help="run folder (default: runs/<algo>_<predictor>_<split>_s<seed>_<time>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        metavar="KEY=VALUE",
        help="override a config key, value as YAML: learning_rate=1e-4, env.time_penalty=-0.01, "
        "policy_kwargs.net_arch=[64,64], eval.episodes=50, pretrain.episodes=300, pretrain=null",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The :class:`TrainConfig` of parsed command-line arguments."""
    if args.resume and not args.out:
        raise ConfigError("--resume needs --out RUN_DIR")
    path = args.config
    if path is None:
        saved = Path(args.out) / "config.yaml" if args.out else None
        path = saved if args.resume and saved is not None and saved.is_file() else DEFAULT_CONFIG
    overrides = parse_set(args.overrides)
    for key in ("predictor", "split", "seed"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    if args.timesteps is not None:
        overrides["n_timesteps"] = args.timesteps
    if not Path(path).is_file():
        raise FileNotFoundError(f"no training config {path}")
    return load_train_config(path, None, overrides)


def run_from_args(args: argparse.Namespace, command: str | None = None) -> int:
    cfg = config_from_args(args)
    run_dir = train(cfg, args.out, resume=args.resume, progress=not args.no_progress, command=command)
    done = json.loads((run_dir / "DONE").read_text())
    best = done.get("best_validation") or {}
    msg = f"run folder {run_dir}: {done['steps']} steps"
    if best:
        msg += f"; best validation success {best['success_rate']:.3f} at step {best['step']}"
    print(msg)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from agents.entry import module_main

    def run(args: argparse.Namespace) -> int:
        return run_from_args(
            args, shlex.join(["python", "-m", "agents.train", *(sys.argv[1:] if argv is None else argv)])
        )

    return module_main("python -m agents.train", __doc__, add_train_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
