"""Training: determinism, checkpoint round-trip and resume, NaN stop, config errors, export."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import crowdnav_mesrnn.training.trainer as training
from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.models.learned import load_predictor
from crowdnav_mesrnn.models.pretrained import export_checkpoint
from crowdnav_mesrnn.training.trainer import Trainer, TrainingDivergedError, load_configs

TINY = {"node_embed": 8, "node_hidden": 16, "edge_embed": 4, "edge_hidden": 8, "max_windows": 24, "batch_size": 8}


def tiny_trainer(out: Path, data_dir: Path, epochs: int = 2) -> Trainer:
    m, t = load_configs("mesrnn", overrides={**TINY, "split": "zara1", "epochs": epochs, "data_dir": str(data_dir)})
    return Trainer(m, t, out)


@pytest.mark.slow
def test_resume_equals_uninterrupted_run(tmp_path: Path, data_dir: Path) -> None:
    straight = tiny_trainer(tmp_path / "a", data_dir)
    straight.fit(progress=False, log=lambda *_: None)
    first = tiny_trainer(tmp_path / "b", data_dir, epochs=1)
    first.fit(progress=False, log=lambda *_: None)
    resumed = tiny_trainer(tmp_path / "b", data_dir, epochs=2)
    resumed.resume()
    assert resumed.epoch == 1
    resumed.fit(progress=False, log=lambda *_: None)
    for k, v in straight.net.state_dict().items():
        torch.testing.assert_close(resumed.net.state_dict()[k], v, rtol=0, atol=0, msg=k)
    assert [h["val_ade_m"] for h in resumed.history] == [h["val_ade_m"] for h in straight.history]
    # best.pt is a lean checkpoint that loads as a predictor with its normalisation.
    pred = load_predictor(tmp_path / "a" / "best.pt", model="mesrnn", split="zara1")
    assert pred.norm == straight.norm
    assert "optimizer" not in torch.load(tmp_path / "a" / "best.pt", weights_only=True)


def test_resume_rejects_a_different_config(tmp_path: Path, data_dir: Path) -> None:
    tiny_trainer(tmp_path / "r", data_dir, epochs=1).fit(progress=False, log=lambda *_: None)
    m, t = load_configs("mesrnn", overrides={**TINY, "split": "zara1", "lr": 0.01, "data_dir": str(data_dir)})
    with pytest.raises(ConfigError, match="differs from this run's in lr"):
        Trainer(m, t, tmp_path / "r").resume()


def test_nan_loss_stops_and_keeps_last_good_checkpoint(
    tmp_path: Path, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    tr = tiny_trainer(tmp_path / "n", data_dir, epochs=2)
    tr.train_epoch(progress=False)
    tr.epoch = 1
    tr.save("last.pt")
    before = (tmp_path / "n" / "last.pt").read_bytes()
    monkeypatch.setattr(training, "masked_loss", lambda *a: torch.tensor(float("nan"), requires_grad=True))
    with pytest.raises(TrainingDivergedError, match="last good checkpoint"):
        tr.fit(progress=False, log=lambda *_: None)
    assert (tmp_path / "n" / "last.pt").read_bytes() == before


def test_config_errors_list_valid_keys(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"valid keys: .*batch_size"):
        load_configs("srnn", overrides={"bach_size": 3})
    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  model: srnn\ntrian:\n  epochs: 1\n")
    with pytest.raises(ConfigError, match="valid keys: model, train"):
        load_configs("srnn", bad)
    with pytest.raises(ConfigError, match="not 'mesrnn'"):
        load_configs("mesrnn", _write(tmp_path, "model:\n  model: srnn\n"))
    with pytest.raises(ValueError, match="valid splits"):
        load_configs("srnn", overrides={"split": "zara3"})


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return p


def test_shipped_yaml_configs_load() -> None:
    for model in ("mesrnn", "srnn", "vlstm"):
        m, t = load_configs(model)
        assert (m.node_hidden, m.edge_hidden, m.node_embed, m.edge_embed) == (256, 128, 128, 64)
        assert t.epochs == 10 and t.lr == 1e-3 and t.grad_clip == 10.0 and t.teacher_forcing
        mv, _ = load_configs(model, training.CONFIG_DIR / f"{model}_residual.yaml")
        assert mv.node_input == "velocity"


def test_cli_train_eval_export(tmp_path: Path, data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    sets = [x for k, v in TINY.items() for x in ("--set", f"{k}={v}")]
    args = [
        "predictor",
        "train",
        "--model",
        "srnn",
        "--split",
        "eth",
        "--epochs",
        "1",
        "--out",
        str(out),
        "--no-progress",
    ]
    assert main([*args, *sets]) == 0
    assert main([*args, *sets]) == 2  # refuses to overwrite without --resume
    assert "pass --resume" in capsys.readouterr().err
    assert (
        main(["predictor", "eval", "--model", "srnn", "--split", "eth", "--checkpoint", str(out / "best.pt"), "--json"])
        == 0
    )
    dest = export_checkpoint(out / "best.pt", "srnn", "eth", "test", dest=tmp_path / "srnn_eth.pt")
    assert dest.stat().st_size < (out / "last.pt").stat().st_size
    with pytest.raises(ValueError, match="not 'zara1'"):
        export_checkpoint(out / "best.pt", "srnn", "zara1", dest=tmp_path / "x.pt")


def test_bf16_precision_trains_and_bad_precision_is_rejected(tmp_path: Path, data_dir: Path) -> None:
    m, t = load_configs(
        "mesrnn",
        overrides={**TINY, "split": "zara1", "epochs": 1, "precision": "bf16", "data_dir": str(data_dir)},
    )
    res = Trainer(m, t, tmp_path / "bf").fit(progress=False, log=lambda *_: None)
    assert res["history"][0]["train_loss"] > 0 and res["best_val_ade_m"] < 10
    assert load_predictor(tmp_path / "bf" / "best.pt").net.decoder.weight.dtype == torch.float32
    with pytest.raises(ConfigError, match="precision must be one of fp32, bf16"):
        load_configs("mesrnn", overrides={"precision": "fp16"})
