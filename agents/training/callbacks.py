"""What runs inside ``learn()``: validation keeping the best model, checkpoints at round boundaries, progress.

Checkpoints are ``checkpoints/step_<n>/`` folders of the run (:func:`save_checkpoint`); ``checkpoints/latest.json``
points at the last one (:func:`latest_checkpoint`), from which ``--resume`` continues.
"""

from __future__ import annotations

import copy
import json
import pickle
import shutil
import threading
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from agents.actions import DiscretePolicy
from agents.rollout import SB3Policy, evaluation_seeds, run_episodes
from agents.stats import wilson_interval
from agents.training.config import TrainConfig
from agents.training.logger import csv_text
from crowdnav_mesrnn.utils import atomic_write, atomic_write_json, atomic_write_text


def save_model(model: Any, path: Path) -> None:
    """An SB3 model saved atomically to ``path`` (``.zip``)."""
    atomic_write(path, lambda fh: model.save(fh))


def save_policy_file(model: Any, model_file: Path, run_dir: Path) -> Path | None:
    """The model as a policy file of the project's format beside ``model_file``: ``<stem>.policy.yaml`` and
    ``<stem>.pt`` (:mod:`agents.policy_file`; data only, so the run's policy loads without ``--trust-pickle``), with
    the run's ``config.yaml`` inside. A policy outside the format's allow-lists (a custom class) gets a warning and
    only the SB3 zip; returns None then."""
    from agents.policy_file import PolicyFileError, policy_file_path, write_policy_file
    from crowdnav_mesrnn.config import load_yaml

    config = load_yaml(run_dir / "config.yaml")
    dest = policy_file_path(model_file)
    source = {"run_dir": str(run_dir), "model": model_file.name, "steps": int(model.num_timesteps)}
    try:
        algo = config["crowdnav_mesrnn"]["algo"]
        return write_policy_file(dest, model.policy, algo, config, model.get_vec_normalize_env(), source)
    except PolicyFileError as exc:
        warnings.warn(
            f"{exc}: the run folder holds the SB3 zip {model_file.name} only, which loads with --trust-pickle",
            UserWarning,
            stacklevel=2,
        )
        return None


def _save_pickle(obj: Any, path: Path) -> None:
    atomic_write(path, lambda fh: pickle.dump(obj, fh))


def save_vecnormalize(model: Any, model_file: Path) -> None:
    """The model's ``VecNormalize`` statistics, if it has any, as ``<model stem>_vecnormalize.pkl`` beside
    ``model_file``."""
    vn = model.get_vec_normalize_env()
    if vn is not None:
        venv, vn.venv = vn.venv, None  # the statistics only: worker processes cannot be pickled
        try:
            _save_pickle(vn, model_file.with_name(f"{model_file.stem}_vecnormalize.pkl"))
        finally:
            vn.venv = venv


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
            save_model(self.model, self.run_dir / "best_model.zip")
            save_vecnormalize(self.model, self.run_dir / "best_model.zip")
            save_policy_file(self.model, self.run_dir / "best_model.zip", self.run_dir)
        self.state["history"].append(result)
        self.state["last_eval_step"] = int(self.num_timesteps)
        atomic_write_text(self.run_dir / "evaluations.csv", csv_text(list(result), self.state["history"]))
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


#: The files every checkpoint folder holds; its ``state.json`` (written last) lists the others it holds. A folder
#: without one of them is incomplete and never resumed from.
CHECKPOINT_FILES = ("model.zip", "state.json")

#: Held while this process writes a checkpoint, and by anything in it that copies a run's checkpoints meanwhile (the
#: Ray task's shipper thread), so a copy never catches a checkpoint half-written or half-pruned.
CHECKPOINT_LOCK = threading.Lock()

#: Folders a checkpoint passes through: ``.step_<n>.partial`` while written, ``.step_<n>.old`` while replaced.
STAGING_SUFFIXES = (".partial", ".old")


def save_checkpoint(model: Any, run_dir: Path, validation_state: Mapping[str, Any], keep: int = 1) -> Path:
    """``checkpoints/step_<n>/`` with ``model.zip``, ``model_vecnormalize.pkl``, ``replay_buffer.pkl`` (off-policy)
    and ``state.json`` (listing the other files); then ``checkpoints/latest.json`` points at it. Then the ``keep - 1``
    newest older checkpoints are kept and the others removed, with any newer one (left by a run this one resumed
    before it: it is not the one resumed from).

    The files are written into a staging folder (``.step_<n>.partial``) renamed into place once all of them are
    there, so a process killed at any moment leaves the complete folder or a staging folder that
    :func:`recover_checkpoints` sorts out (staging folders left by a killed save are cleared at the next save)."""
    steps = int(model.num_timesteps)
    root = run_dir / "checkpoints"
    folder = root / f"step_{steps:010d}"
    staging = root / f".{folder.name}.partial"
    with CHECKPOINT_LOCK:
        _clear_staging(root)
        save_model(model, staging / "model.zip")
        save_vecnormalize(model, staging / "model.zip")
        if getattr(model, "replay_buffer", None) is not None:
            atomic_write(staging / "replay_buffer.pkl", lambda fh: model.save_replay_buffer(fh))
        files = sorted(p.name for p in staging.iterdir() if p.is_file())
        state = {"steps": steps, "validation": validation_state, "files": files}
        atomic_write_json(staging / "state.json", state)
        if folder.exists():  # a second checkpoint at the same step (an interrupt right after a periodic one)
            old = root / f".{folder.name}.old"
            folder.rename(old)  # killed before the next rename: recover_checkpoints renames the staging folder
            staging.rename(folder)
            shutil.rmtree(old, ignore_errors=True)
        else:
            staging.rename(folder)
        atomic_write_json(root / "latest.json", {"steps": steps, "folder": folder.name})
        others = sorted(p for p in root.glob("step_*") if p.is_dir() and p != folder)
        older = [p for p in others if p.name < folder.name]  # zero-padded: names sort by step
        newer = [p for p in others if p.name > folder.name]
        for gone in newer + older[: max(0, len(older) - (keep - 1))]:
            shutil.rmtree(gone, ignore_errors=True)
    return folder


def _clear_staging(root: Path) -> None:
    for path in root.glob(".step_*"):
        if path.is_dir() and path.name.endswith(STAGING_SUFFIXES):
            shutil.rmtree(path, ignore_errors=True)


def checkpoint_complete(folder: Path) -> bool:
    """Whether ``folder`` holds every file of a checkpoint: :data:`CHECKPOINT_FILES` and those its ``state.json``
    lists (checkpoints written before the list existed: :data:`CHECKPOINT_FILES` only)."""
    try:
        state = json.loads((folder / "state.json").read_text())
    except (OSError, ValueError):
        return False
    required = checkpoint_required_files(state)
    return required is not None and all((folder / name).is_file() for name in required)


def checkpoint_required_files(state: Any) -> tuple[str, ...] | None:
    """The files a checkpoint whose ``state.json`` holds ``state`` must have: :data:`CHECKPOINT_FILES` and those
    the state lists (checkpoints written before the list existed: :data:`CHECKPOINT_FILES` only); None when the
    state is malformed (such a checkpoint is never complete). One rule for a folder on disk and a packed one."""
    listed = state.get("files", []) if isinstance(state, dict) else None
    if not isinstance(listed, list) or not all(isinstance(name, str) for name in listed):
        return None
    return (*CHECKPOINT_FILES, *listed)


def recover_checkpoints(run_dir: Path) -> None:
    """Before a resume: a complete staging folder whose ``step_<n>`` is missing (a save killed between its renames)
    is renamed into place; every other staging folder is removed."""
    root = run_dir / "checkpoints"
    with CHECKPOINT_LOCK:
        for suffix in STAGING_SUFFIXES:  # the newer files first: .partial was written after .old
            for path in sorted(root.glob(f".step_*{suffix}")):
                target = root / path.name[1 : -len(suffix)]
                if path.is_dir() and not target.exists() and checkpoint_complete(path):
                    path.rename(target)
        _clear_staging(root)


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The folder ``checkpoints/latest.json`` points at if it is complete (:func:`checkpoint_complete`); otherwise
    the newest complete ``step_<n>`` folder (a pointer can outlive its folder, e.g. in a copy taken while a run wrote
    a new one); None when there is no complete checkpoint."""
    root = run_dir / "checkpoints"
    pointer = root / "latest.json"
    if pointer.is_file():
        try:
            name = json.loads(pointer.read_text())["folder"]
        except (ValueError, KeyError, TypeError):
            name = None
        if isinstance(name, str) and checkpoint_complete(root / name):
            return root / name
    complete = sorted(p for p in root.glob("step_*") if p.is_dir() and checkpoint_complete(p))
    return complete[-1] if complete else None
