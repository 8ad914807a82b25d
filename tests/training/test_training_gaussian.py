"""Training the distribution head: the decoupled recipe leaves the point forecast's training untouched, NLL
selection and its checkpoints, config errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.models.learned import load_predictor
from crowdnav_mesrnn.training.trainer import Trainer, load_configs

TINY = {"node_embed": 8, "node_hidden": 16, "edge_embed": 4, "edge_hidden": 8, "max_windows": 24, "batch_size": 8}
DECOUPLED = {"head": "gaussian", "scale_detach": True, "mean_loss": "mse", "scale_lr": 0.01, "select_on": "nll"}


def trainer(out: Path, data_dir: Path, **extra: object) -> Trainer:
    over = {**TINY, "split": "zara1", "epochs": 2, "data_dir": str(data_dir), **extra}
    m, t = load_configs("srnn", "configs/predictor/srnn_residual.yaml", over)
    return Trainer(m, t, out)


@pytest.mark.slow
def test_decoupled_head_trains_the_means_exactly_as_the_point_head(tmp_path: Path, data_dir: Path) -> None:
    point = trainer(tmp_path / "p", data_dir)
    point.fit(progress=False, log=lambda *_: None)
    dist = trainer(tmp_path / "g", data_dir, **DECOUPLED)
    dist.fit(progress=False, log=lambda *_: None)
    got = dist.net.state_dict()
    for key, value in point.net.state_dict().items():
        torch.testing.assert_close(got[key], value, rtol=0, atol=0, msg=key)
    assert dist.net.step_bias.abs().sum() > 0  # the head did learn
    assert [h["val_ade_m"] for h in dist.history] == [h["val_ade_m"] for h in point.history]
    assert all("val_nll_m" in h for h in dist.history)
    # best.pt is the epoch of lowest validation NLL, with the head; the run records the selection
    best = min(dist.history, key=lambda h: h["val_nll_m"])
    ck = torch.load(tmp_path / "g" / "best.pt", weights_only=True)
    assert ck["epoch"] == best["epoch"] and ck["select_on"] == "nll"
    assert ck["best_val_nll_m"] == pytest.approx(best["val_nll_m"])
    assert ck["best_val_ade_m"] == pytest.approx(best["val_ade_m"])
    assert load_predictor(tmp_path / "g" / "best.pt", split="zara1").has_distribution


def test_resume_keeps_the_nll_selection(tmp_path: Path, data_dir: Path) -> None:
    first = trainer(tmp_path / "r", data_dir, **{**DECOUPLED, "epochs": 1})
    first.fit(progress=False, log=lambda *_: None)
    again = trainer(tmp_path / "r", data_dir, **DECOUPLED)
    again.resume()
    assert again.best_val == pytest.approx(first.history[0]["val_nll_m"]) and again.best_row == first.history[0]


def test_head_options_are_checked() -> None:
    with pytest.raises(ConfigError, match="select_on: nll needs a distribution head"):
        load_configs("srnn", overrides={"select_on": "nll"})
    with pytest.raises(ConfigError, match="mean_loss must be"):
        load_configs("srnn", overrides={"head": "gaussian", "mean_loss": "l1"})
    with pytest.raises(ConfigError, match="nll_beta must lie"):
        load_configs("srnn", overrides={"head": "gaussian", "nll_beta": 2.0})
    with pytest.raises(ConfigError, match="scale_lr must be"):
        load_configs("srnn", overrides={"head": "gaussian", "scale_lr": -1.0})
