"""Denser training crowds from the training recordings alone (``crowd_overlays``): the overlay itself on a
constructed crowd, and that training episodes with the option on never read the held-out scene."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import SPLIT_TEST_RECORDINGS
from envs.config import episode_recordings
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import make_recording, overlay_recording

REPO = Path(__file__).resolve().parents[2]


def walkers(num_frames: int = 40) -> Any:
    """Five pedestrians walking along x at 1 m/s (0.4 m per frame), entering at frames 0, 5, ..., 20 for 15 frames."""
    positions = np.zeros((num_frames, 5, 2))
    present = np.zeros((num_frames, 5), dtype=bool)
    for p in range(5):
        frames = np.arange(5 * p, 5 * p + 15)
        present[frames, p] = True
        positions[frames, p, 0] = 0.4 * (frames - 5 * p)
        positions[frames, p, 1] = p
    return make_recording("walkers", positions, present)


def max_step_m(rec: Any) -> float:
    both = rec.present[1:] & rec.present[:-1]
    step = np.linalg.norm(np.diff(rec.positions, axis=0), axis=-1)
    return float(step[both].max())


def test_copies_are_evenly_shifted_within_the_window_and_never_jump() -> None:
    rec = walkers()
    dense = overlay_recording(rec, 2)
    assert dense.name == rec.name and np.array_equal(dense.frames, rec.frames)
    np.testing.assert_array_equal(dense.present[:, :5], rec.present)  # the original is kept as it is
    counts = rec.present.sum(axis=1)
    width = len(counts)
    expected = counts + sum(np.roll(counts, round(j * width / 3)) for j in (1, 2))
    np.testing.assert_array_equal(dense.present.sum(axis=1), expected)
    assert max_step_m(dense) == pytest.approx(max_step_m(rec))  # tracks cut at the wrap: nobody teleports
    assert len(np.unique(dense.ped_ids)) == len(dense.ped_ids) and np.all(np.diff(dense.ped_ids) > 0)
    assert overlay_recording(rec, 0) is rec


def test_frames_outside_the_window_keep_only_the_original_pedestrians() -> None:
    rec = walkers()
    times = rec.times_s()
    cut = float(times[30])
    dense = overlay_recording(rec, 3, (0.0, cut))
    outside = times >= cut - 1e-9
    np.testing.assert_array_equal(dense.present[outside].sum(axis=1), rec.present[outside].sum(axis=1))
    assert (dense.present[~outside].sum() - rec.present[~outside].sum()) == 3 * rec.present[~outside].sum()
    # every copy's pedestrian comes from frames inside the window: its positions are ones the window holds
    inside_positions = {tuple(p) for p in rec.positions[~outside][rec.present[~outside]].round(9)}
    copied = dense.positions[:, 5:][dense.present[:, 5:]].round(9)
    assert {tuple(p) for p in copied} <= inside_positions


def test_the_held_out_scene_cannot_be_overlaid() -> None:
    with pytest.raises(ConfigError, match=r"crowd_overlays.*part 'train'"):
        CrowdNavEnv(crowd="synthetic", part="test", crowd_overlays=1)


def test_synthetic_training_crowd_gets_denser() -> None:
    plain = CrowdNavEnv(crowd="synthetic", predictor="none", synthetic_duration_s=120.0)
    dense = CrowdNavEnv(crowd="synthetic", predictor="none", synthetic_duration_s=120.0, crowd_overlays=2)
    assert dense.crowd_kind == "synthetic+2 overlays"
    assert dense.recordings[0].present.sum() == 3 * plain.recordings[0].present.sum()


def test_training_episodes_with_overlays_never_read_the_held_out_recordings(
    data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from agents.evaluation.run import evaluation_env_kwargs
    from agents.training.config import load_train_config
    from crowdnav_mesrnn.data import recordings as data_recordings
    from envs import crowd_nav

    read: list[str] = []
    real = data_recordings.load_recording

    def spy(name: str, *args: Any, **kwargs: Any) -> Any:
        read.append(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(crowd_nav, "load_recording", spy)
    cfg = load_train_config(
        REPO / "configs" / "agent" / "ppo.yaml",
        None,
        {"split": "univ", "predictor": "none", "train_env.crowd_overlays": 2},
    )
    assert "crowd_overlays" not in cfg.env_kwargs("val")  # validation replays the training scenes as recorded
    assert "crowd_overlays" not in evaluation_env_kwargs("planner", "none", "univ", cfg.env)
    env = CrowdNavEnv(**cfg.env_kwargs("train"))
    held_out = set(SPLIT_TEST_RECORDINGS["univ"])
    training = set(episode_recordings("univ", "train"))
    densities = []
    for seed in range(12):
        _, info = env.reset(seed=seed)
        assert info["recording"] in training and info["crowd"] == "replay+2 overlays"
        densities.append(info["crowd_density"])
    assert read and not held_out & set(read) and set(read) <= training
    plain = CrowdNavEnv(**cfg.env_kwargs("val"), crowd_overlays=0)
    plain_env = CrowdNavEnv(**{**cfg.env_kwargs("train"), "crowd_overlays": 0})
    assert plain.crowd_kind == "replay"
    plain_densities = [plain_env.reset(seed=seed)[1]["crowd_density"] for seed in range(12)]
    assert np.mean(densities) > 1.5 * np.mean(plain_densities)


def test_validation_may_be_denser_but_evaluation_never_is(tmp_path: Path) -> None:
    from agents.training import load_train_config, train

    over = {
        "predictor": "none", "n_envs": 1, "n_timesteps": 64, "n_steps": 64, "batch_size": 32, "n_epochs": 1,
        "pretrain": None, "eval.episodes": 2, "eval.n_envs": 1, "checkpoint_freq_steps": 0, "env.crowd": "synthetic",
        "policy_kwargs.net_arch": [8], "policy_kwargs.features_extractor_kwargs.hidden_dim": 4,
        "train_env.crowd_overlays": 1, "val_env.crowd_overlays": 2,
    }  # fmt: skip
    cfg = load_train_config(REPO / "configs" / "agent" / "ppo.yaml", None, over)
    assert cfg.env_kwargs("val")["crowd_overlays"] == 2 and cfg.env_kwargs("train")["crowd_overlays"] == 1
    assert CrowdNavEnv(**cfg.env_kwargs("val")).crowd_kind == "synthetic+2 overlays"
    run = train(cfg, tmp_path / "dense", progress=False)
    from agents.evaluation.run import evaluation_env_kwargs

    assert "crowd_overlays" not in evaluation_env_kwargs(run, "none", "zara1")
    with pytest.raises(ConfigError, match="val_env must be a mapping"):
        load_train_config(REPO / "configs" / "agent" / "ppo.yaml", None, {"val_env": 3})
