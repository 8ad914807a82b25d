""":func:`train`: a policy trained (or resumed) from a :class:`~agents.training.config.TrainConfig` into a run folder.

## Episodes
Training episodes replay the split's four training scenes (``part="train"``) in the first
``1 - val_fraction`` of each recording (``episode_time="train"``); validation episodes replay the same
scenes' last ``val_fraction`` (``episode_time="val"``) — never the held-out test scene.

## A run folder
``config.yaml`` (the resolved config in the same layout, plus a ``run`` section: predictor, split, seed,
environment id, the resolved environment settings, the crowd replayed (``crowd``: ``kind`` and ETH/UCY
``data_dir``), sha256 of the predictor weights involved, code version), ``command.txt``, ``version.txt``,
``progress.csv`` (SB3's logger), ``evaluations.csv`` (validation history), ``best_model.zip`` (best validation
success rate, ties broken by return), ``final_model.zip`` (``*_vecnormalize.pkl`` beside the models when
observations are normalised; each model also as a policy file of the project's format, ``<stem>.policy.yaml`` and
``<stem>.pt``, which loads without unpickling: :mod:`agents.policy_file`), ``pretrain.json`` (warm start), ``checkpoints/`` (model, ``VecNormalize``
statistics, SAC's replay buffer and the validation state every ``checkpoint_freq_steps``; ``--resume`` continues
from the latest with the same timestep count), ``tb/`` (TensorBoard, when installed) and ``DONE``, written last.
Every file is written atomically.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
import shlex
import sys
import time
import warnings
from collections.abc import Mapping
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

import yaml

from agents.actions import DiscreteActionWrapper, action_set
from agents.rollout import prepare_forecasts
from agents.runs import PROJECT_KEY
from agents.scoring import attach_geometry_cache
from agents.training.callbacks import (
    Checkpoint,
    Progress,
    Validation,
    latest_checkpoint,
    recover_checkpoints,
    save_model,
    save_policy_file,
    save_vecnormalize,
)
from agents.training.config import TrainConfig, _algo_class, algorithm_kwargs, policy_class, vec_env_kind
from agents.training.logger import make_logger
from agents.training.pretrain import pretrain
from agents.vec_env import CrowdVecEnv
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError, load_yaml
from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text, code_version
from envs.config import config_from, crowd_source, episode_recordings


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
        env = DiscreteActionWrapper(env, actions)
    return Monitor(SuccessInfo(env))


def make_vec_env(cfg: TrainConfig) -> Any:
    """The training ``VecEnv`` of ``vec_env`` (:attr:`~agents.training.config.TrainConfig.vec_env`; under ``auto``
    the batched environment, or with a warning naming why, ``SubprocVecEnv`` with the forkserver start method for
    2+ environments and ``DummyVecEnv`` for one), wrapped in ``VecNormalize`` when configured. Every choice gives
    the transitions of ``DummyVecEnv`` over :func:`make_env`'s environments."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    kind, why = vec_env_kind(cfg)
    if why is not None:
        warnings.warn(
            f"vec_env 'auto' steps the training environments with {kind!r}, not the batched environment: {why}",
            UserWarning,
            stacklevel=2,
        )
    if kind == "vector":
        from agents.batched_vec_env import BatchedVecEnv

        venv: Any = BatchedVecEnv(cfg.n_envs, cfg.env_kwargs("train"), cfg.action_set())
    elif kind == "batched":
        from envs.crowd_nav import CrowdNavEnv

        bare = [partial(CrowdNavEnv, **cfg.env_kwargs("train")) for _ in range(cfg.n_envs)]
        venv = CrowdVecEnv(bare, cfg.action_set())
    else:
        fns = [partial(make_env, cfg.env_kwargs("train"), cfg.action) for _ in range(cfg.n_envs)]
        venv = SubprocVecEnv(fns, start_method="forkserver") if kind == "subproc" else DummyVecEnv(fns)
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
    environments replay: ``{"kind": "replay", "data_dir": ...}`` or ``{"kind": "synthetic", ...}``, and ``env_rules``,
    the rules the environments run under: :func:`envs.crowd_nav.env_rules`).

    Raises:
        DataNotFoundError: the run replays ETH/UCY scenes (``env.crowd`` ``auto`` or ``replay``) and the data is not
            found.
    """
    from envs.crowd_nav import env_rules

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
        # the environment's rules (revision, reaction model and its revision): a run trained under other rules is
        # told apart from its config.yaml alone
        "env_rules": env_rules(env_cfg),
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
    if resume:
        recover_checkpoints(run_dir)
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
        save_model(model, run_dir / "final_model.zip")
        save_vecnormalize(model, run_dir / "final_model.zip")
        save_policy_file(model, run_dir / "final_model.zip", run_dir)
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
