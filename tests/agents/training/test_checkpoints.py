"""Checkpoint folders appear whole or not at all, and a resume uses only a complete one."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from stable_baselines3 import PPO

import agents.training.callbacks as callbacks
from agents.training.callbacks import checkpoint_complete, latest_checkpoint, recover_checkpoints, save_checkpoint


@pytest.fixture(scope="module")
def model() -> Any:
    return PPO("MlpPolicy", "CartPole-v1", n_steps=16, batch_size=16, device="cpu", seed=0)


def _write_checkpoint(
    root: Path, steps: int, files: tuple[str, ...] = ("model.zip", "state.json"), listed: tuple[str, ...] = ()
) -> Path:
    folder = root / "checkpoints" / f"step_{steps:010d}"
    folder.mkdir(parents=True)
    for name in files:
        state = {"steps": steps, "files": ["model.zip", *listed]}
        (folder / name).write_text(json.dumps(state) if name == "state.json" else "weights")
    return folder


def _names(run: Path) -> list[str]:
    return sorted(p.name for p in (run / "checkpoints").iterdir())


def test_a_save_killed_before_its_state_file_leaves_no_step_folder_and_the_previous_checkpoint(
    tmp_path: Path, model: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    model.num_timesteps = 64
    first = save_checkpoint(model, tmp_path, {"best": None})
    assert checkpoint_complete(first) and latest_checkpoint(tmp_path) == first
    original = callbacks.atomic_write_json

    def killed(path: Path, obj: Any) -> None:  # the process dies between the model and its state file
        if path.name == "state.json":
            raise KeyboardInterrupt
        original(path, obj)

    monkeypatch.setattr(callbacks, "atomic_write_json", killed)
    model.num_timesteps = 128
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(model, tmp_path, {"best": None})
    monkeypatch.undo()
    assert not (tmp_path / "checkpoints" / "step_0000000128").exists()
    assert latest_checkpoint(tmp_path) == first
    # the next save clears the staging folder the killed one left and completes
    second = save_checkpoint(model, tmp_path, {"best": None})
    assert checkpoint_complete(second) and latest_checkpoint(tmp_path) == second
    assert _names(tmp_path) == ["latest.json", "step_0000000128"]


def test_a_second_save_at_the_same_step_replaces_the_folder(tmp_path: Path, model: Any) -> None:
    model.num_timesteps = 64
    save_checkpoint(model, tmp_path, {"best": None})
    folder = save_checkpoint(model, tmp_path, {"best": {"success_rate": 0.5}})
    assert json.loads((folder / "state.json").read_text())["validation"] == {"best": {"success_rate": 0.5}}
    assert _names(tmp_path) == ["latest.json", folder.name]


def test_a_save_killed_between_the_renames_of_a_same_step_replace_is_recovered(
    tmp_path: Path, model: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    model.num_timesteps = 64
    save_checkpoint(model, tmp_path, {"best": None})
    original = Path.rename

    def rename(self: Path, target: Any) -> Any:  # killed after the old folder moved away, before the new moved in
        if self.name.endswith(".partial") and (self.parent / f".{Path(target).name}.old").exists():
            raise KeyboardInterrupt
        return original(self, target)

    monkeypatch.setattr(Path, "rename", rename)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(model, tmp_path, {"best": {"success_rate": 0.5}})
    monkeypatch.undo()
    assert "step_0000000064" not in _names(tmp_path)
    recover_checkpoints(tmp_path)  # what a resume does first
    ckpt = latest_checkpoint(tmp_path)
    assert ckpt is not None and ckpt.name == "step_0000000064"
    assert json.loads((ckpt / "state.json").read_text())["validation"] == {"best": {"success_rate": 0.5}}
    assert _names(tmp_path) == ["latest.json", "step_0000000064"]


def test_a_checkpoint_lists_its_optional_files_and_is_incomplete_without_one(tmp_path: Path) -> None:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    normalised = PPO("MlpPolicy", VecNormalize(make_vec_env("CartPole-v1", n_envs=1)), n_steps=16, batch_size=16)
    normalised.num_timesteps = 32
    folder = save_checkpoint(normalised, tmp_path, {"best": None})
    listed = json.loads((folder / "state.json").read_text())["files"]
    assert listed == ["model.zip", "model_vecnormalize.pkl"] and checkpoint_complete(folder)
    (folder / "model_vecnormalize.pkl").unlink()  # e.g. a copy that caught the folder while it was pruned
    assert not checkpoint_complete(folder) and latest_checkpoint(tmp_path) is None


def test_a_save_after_resuming_from_an_older_checkpoint_keeps_itself_and_drops_the_abandoned_newer_one(
    tmp_path: Path, model: Any
) -> None:
    _write_checkpoint(tmp_path, 128)
    _write_checkpoint(tmp_path, 256)  # a run killed after this folder was renamed in, before its pointer
    (tmp_path / "checkpoints" / "latest.json").write_text(json.dumps({"steps": 128, "folder": "step_0000000128"}))
    model.num_timesteps = 192  # the resumed run (from 128) saves at 192
    folder = save_checkpoint(model, tmp_path, {"best": None})
    assert _names(tmp_path) == ["latest.json", folder.name] and latest_checkpoint(tmp_path) == folder
    model.num_timesteps = 320
    newest = save_checkpoint(model, tmp_path, {"best": None}, keep=2)
    assert _names(tmp_path) == ["latest.json", folder.name, newest.name]


def test_staging_folders_a_killed_save_left_are_cleared_at_the_next_save(tmp_path: Path, model: Any) -> None:
    for name in (".step_0000000096.partial", ".step_0000000032.old"):
        (tmp_path / "checkpoints" / name).mkdir(parents=True)
        (tmp_path / "checkpoints" / name / "model.zip").write_text("half")
    model.num_timesteps = 128
    folder = save_checkpoint(model, tmp_path, {"best": None})
    assert _names(tmp_path) == ["latest.json", folder.name]


@pytest.mark.parametrize("missing", ["state.json", "model_vecnormalize.pkl"])
def test_a_pointer_to_an_incomplete_folder_falls_back_to_the_newest_complete_one(tmp_path: Path, missing: str) -> None:
    complete = _write_checkpoint(tmp_path, 128)
    files = tuple(n for n in ("model.zip", "model_vecnormalize.pkl", "state.json") if n != missing)
    _write_checkpoint(tmp_path, 256, files=files, listed=("model_vecnormalize.pkl",))  # caught without one file
    (tmp_path / "checkpoints" / "latest.json").write_text(json.dumps({"steps": 256, "folder": "step_0000000256"}))
    assert latest_checkpoint(tmp_path) == complete


def test_a_pointer_to_a_removed_folder_falls_back_and_none_complete_means_none(tmp_path: Path) -> None:
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "latest.json").write_text(json.dumps({"steps": 64, "folder": "step_0000000064"}))
    assert latest_checkpoint(tmp_path) is None
    _write_checkpoint(tmp_path, 32, files=("state.json",))
    assert latest_checkpoint(tmp_path) is None
    assert latest_checkpoint(tmp_path / "nowhere") is None
    complete = _write_checkpoint(tmp_path, 16)
    assert latest_checkpoint(tmp_path) == complete


@pytest.mark.parametrize(
    "state", [None, [], {"files": "model_vecnormalize.pkl"}, {"files": [1]}, {"files": ["a.pkl", None]}]
)
def test_a_malformed_state_names_no_files_and_its_folder_is_never_complete(tmp_path: Path, state: Any) -> None:
    folder = tmp_path / "step_0000000064"
    folder.mkdir()
    for name in ("model.zip", "a.pkl", "1"):
        (folder / name).write_bytes(b"x")
    (folder / "state.json").write_text(json.dumps(state))
    assert callbacks.checkpoint_required_files(state) is None
    assert not checkpoint_complete(folder)


def test_the_files_a_state_requires_are_the_fixed_ones_and_those_it_lists() -> None:
    assert callbacks.checkpoint_required_files({"steps": 64}) == callbacks.CHECKPOINT_FILES
    listed = callbacks.checkpoint_required_files({"steps": 64, "files": ["model_vecnormalize.pkl"]})
    assert listed == (*callbacks.CHECKPOINT_FILES, "model_vecnormalize.pkl")
