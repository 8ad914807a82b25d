"""Training interrupted mid-rollout: the checkpoint it leaves is the last round boundary, so the resumed run ends at
exactly its budget."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from stable_baselines3 import PPO

from agents.training.callbacks import Checkpoint
from agents.training.config import load_train_config
from agents.training.run import train


def _interrupt_at(monkeypatch: pytest.MonkeyPatch, step: int) -> None:
    """A KeyboardInterrupt (Ctrl-C) raised by the first env step at or past ``step`` (inside a rollout)."""
    original = Checkpoint._on_step

    def on_step(self: Any) -> bool:
        if self.model.num_timesteps >= step and not getattr(self, "_fired", False):
            self._fired = True
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(Checkpoint, "_on_step", on_step)


@pytest.mark.parametrize("normalize", [False, True])
def test_an_interrupt_mid_rollout_resumes_to_exactly_the_budget(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, normalize: bool, tiny: Any, config_of: Any
) -> None:
    # rounds of 64 steps, a checkpoint every 1000 (so only the interrupt writes one), 256 steps in all
    over = tiny("ppo", "none", steps=256, checkpoint_freq_steps=1000, **{"eval.freq_steps": 0})
    over["pretrain"] = None
    if normalize:
        over["normalize"] = True
    cfg = load_train_config(config_of("ppo"), None, over)
    run = tmp_path / "run"
    _interrupt_at(monkeypatch, 100)  # inside the second round (steps 64-128)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, run, progress=False, command="pytest")
    latest = json.loads((run / "checkpoints" / "latest.json").read_text())
    assert latest["steps"] == 64  # the round boundary, not step 100
    monkeypatch.undo()
    train(cfg, run, resume=True, progress=False, command="pytest")
    assert json.loads((run / "DONE").read_text())["steps"] == 256
    assert "# resumed from step_0000000064" in (run / "command.txt").read_text()


def test_an_interrupt_during_the_update_keeps_the_last_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, tiny: Any, config_of: Any
) -> None:
    over = tiny("ppo", "none", steps=256, checkpoint_freq_steps=64, **{"eval.freq_steps": 0})
    over["pretrain"] = None
    cfg = load_train_config(config_of("ppo"), None, over)
    run = tmp_path / "run"
    original = PPO.train
    calls = {"n": 0}

    def train_step(self: Any) -> None:  # the gradient update of the second round is interrupted
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        original(self)

    monkeypatch.setattr(PPO, "train", train_step)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, run, progress=False, command="pytest")
    # half-updated weights are not saved: the checkpoint is the one at the start of the second round
    assert json.loads((run / "checkpoints" / "latest.json").read_text())["steps"] == 64
    monkeypatch.undo()
    train(cfg, run, resume=True, progress=False, command="pytest")
    assert json.loads((run / "DONE").read_text())["steps"] == 256
