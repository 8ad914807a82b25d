"""Checkpoint folders appear whole or not at all, and a resume uses only a complete one."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from stable_baselines3 import PPO

import agents.training.callbacks as callbacks
from agents.training.callbacks import checkpoint_complete, latest_checkpoint, save_checkpoint


@pytest.fixture(scope="module")
def model() -> Any:
    return PPO("MlpPolicy", "CartPole-v1", n_steps=16, batch_size=16, device="cpu", seed=0)


def _write_checkpoint(root: Path, steps: int, files: tuple[str, ...] = ("model.zip", "state.json")) -> Path:
    folder = root / "checkpoints" / f"step_{steps:010d}"
    folder.mkdir(parents=True)
    for name in files:
        (folder / name).write_text(json.dumps({"steps": steps}) if name == "state.json" else "weights")
    return folder


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
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["latest.json", "step_0000000128"]


def test_a_second_save_at_the_same_step_replaces_the_folder(tmp_path: Path, model: Any) -> None:
    model.num_timesteps = 64
    save_checkpoint(model, tmp_path, {"best": None})
    folder = save_checkpoint(model, tmp_path, {"best": {"success_rate": 0.5}})
    assert json.loads((folder / "state.json").read_text())["validation"] == {"best": {"success_rate": 0.5}}
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["latest.json", folder.name]


def test_a_pointer_to_an_incomplete_folder_falls_back_to_the_newest_complete_one(tmp_path: Path) -> None:
    complete = _write_checkpoint(tmp_path, 128)
    _write_checkpoint(tmp_path, 256, files=("model.zip",))  # caught without its state file
    (tmp_path / "checkpoints" / "latest.json").write_text(json.dumps({"steps": 256, "folder": "step_0000000256"}))
    assert latest_checkpoint(tmp_path) == complete


def test_a_pointer_to_a_removed_folder_falls_back_and_none_complete_means_none(tmp_path: Path) -> None:
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "latest.json").write_text(json.dumps({"steps": 64, "folder": "step_0000000064"}))
    assert latest_checkpoint(tmp_path) is None
    _write_checkpoint(tmp_path, 32, files=("state.json",))
    assert latest_checkpoint(tmp_path) is None
    assert latest_checkpoint(tmp_path / "nowhere") is None
