"""``predictor fit-head``: the gaussian head fitted on point weights with the trunk frozen (crowdnav_mesrnn.training.head_fit)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import PRED_LEN
from crowdnav_mesrnn.data.windows import collate, split_windows
from crowdnav_mesrnn.evaluation.protocol import split_norm
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.architecture import ModelConfig
from crowdnav_mesrnn.models.learned import CHECKPOINT_FORMAT, CheckpointError, lean_state, load_predictor
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
from crowdnav_mesrnn.training.head_fit import (
    HEAD_KEYS,
    HeadFitConfig,
    HeadRows,
    fit_head,
    fit_head_on_rows,
    gaussian_network,
    head_rows,
)
from crowdnav_mesrnn.utils import file_sha256

TINY = {"node_embed": 8, "node_hidden": 16, "edge_embed": 4, "edge_hidden": 8}
RESIDUAL = {"aggregate": "mean", "node_input": "velocity", "offset": "cv_residual"}
FAST = HeadFitConfig(max_windows=16, max_epochs=15, patience=15)


def point_checkpoint(path: Path, data_dir: Path, split: str = "zara1") -> Path:
    """Random point weights of a tiny SRNN for ``split``, saved as training's export saves them."""
    torch.manual_seed(0)
    net = StructuralRNN(ModelConfig(model="srnn", **TINY, **RESIDUAL))
    with torch.no_grad():  # a decoder that is not exactly constant velocity
        net.decoder.weight.normal_(0.0, 0.1)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "model_config": net.cfg.to_dict(),
        "train_config": {"split": split, "min_scored": 2},
        "norm": split_norm(split, data_dir).to_dict(),
        "state_dict": lean_state(net),
    }
    torch.save(payload, path)
    return path


def test_the_fit_changes_only_the_head_and_lowers_validation_nll(tmp_path: Path, data_dir: Path) -> None:
    src = point_checkpoint(tmp_path / "srnn_zara1.pt", data_dir)
    before = file_sha256(src)
    record = fit_head(src, tmp_path / "srnn_gaussian_zara1.pt", FAST, model="srnn", split="zara1", log=None)
    assert file_sha256(src) == before  # the point weights are not touched
    assert record["val_nll_m"] < record["val_nll_m_before"] - 0.1
    assert record["source_sha256"] == before and record["selected_epoch"] >= 1
    point, fitted = load_predictor(src), load_predictor(tmp_path / "srnn_gaussian_zara1.pt", "srnn", "zara1")
    assert fitted.has_distribution and fitted.net.cfg.scale_detach
    trunk = fitted.net.state_dict()
    for key, value in point.net.state_dict().items():
        assert torch.equal(trunk[key], value), key
    # the point forecast is that of the point weights, to the bit
    pos, pres, _ = collate(split_windows("zara1", "val", 2, data_dir)[:8])
    pos_t, pres_t = torch.from_numpy(pos), torch.from_numpy(pres)
    assert torch.equal(fitted.predict_batch(pos_t, pres_t), point.predict_batch(pos_t, pres_t))
    # the file holds the head only, with the record of how it was made
    saved = torch.load(tmp_path / "srnn_gaussian_zara1.pt", weights_only=True)
    assert sorted(saved["state_dict"]) == sorted(HEAD_KEYS)
    assert saved["base"] == {"file": "srnn_zara1.pt", "sha256": before}
    assert "not the declared plan" in saved["selection"]["note"]
    assert saved["head_fit"]["val_nll_m"] == pytest.approx(record["val_nll_m"])


def test_the_cached_node_states_are_those_the_head_reads(data_dir: Path) -> None:
    """The rows' states, through a head, give the raw output of the gaussian network's own rollout."""
    torch.manual_seed(1)
    point = StructuralRNN(ModelConfig(model="srnn", **TINY, **RESIDUAL)).eval()
    net = gaussian_network(point)
    with torch.no_grad():
        net.scale_head.weight.normal_(0.0, 1.0)
        net.step_bias.normal_(0.0, 0.1)
    norm = split_norm("zara1", data_dir)
    windows = split_windows("zara1", "val", 2, data_dir)[:6]
    rows = head_rows(point, norm, windows, "scored")
    pos, pres, scored = collate(windows)
    pos_t, pres_t = torch.from_numpy(pos), torch.from_numpy(pres)
    normed = torch.where(pres_t.unsqueeze(-1), norm.normalise(pos_t), torch.zeros_like(pos_t))
    with torch.no_grad():
        mean, sigma, rho = net.rollout_distribution(normed[:, :8], pres_t[:, :8], PRED_LEN)
        raw = torch.nn.functional.linear(rows.states, net.scale_head.weight, net.scale_head.bias)
        s_rows, r_rows = gaussian.params_from_raw(raw + net.step_bias[rows.ahead])
    keep = torch.from_numpy(scored)[:, None, :].expand(-1, PRED_LEN, -1)
    torch.testing.assert_close(s_rows, sigma[keep])
    torch.testing.assert_close(r_rows, rho[keep])
    torch.testing.assert_close(rows.error, (normed[:, 8:] - mean)[keep].float())


def test_fit_recovers_a_known_heteroscedastic_gaussian() -> None:
    """Rows drawn from Gaussians whose scale follows the state: the fitted head's validation NLL reaches that of the
    true parameters (which the fit never sees) and is far below the untrained head's."""
    gen = torch.Generator().manual_seed(0)
    n, h = 20_000, 16
    torch.manual_seed(0)
    net = gaussian_network(StructuralRNN(ModelConfig(model="vlstm", node_embed=8, node_hidden=h)))

    def draw() -> tuple[HeadRows, torch.Tensor]:
        states = 0.01 * torch.randn(n, h, generator=gen)  # node states vary little, as the real ones do
        ahead = torch.randint(0, PRED_LEN, (n,), generator=gen)
        sigma = (0.01 + 0.005 * ahead.float())[:, None] * torch.exp(40.0 * states[:, :2])
        err = sigma * torch.randn(n, 2, generator=gen)
        return HeadRows(states, err, ahead), gaussian.nll(err.double(), sigma.double(), torch.zeros(n).double())

    train, (val, true_nll) = draw()[0], draw()
    history = fit_head_on_rows(net, train, val, HeadFitConfig(max_epochs=100, patience=10))
    best = history[history[0]["selected_epoch"]]["val_nll"]
    assert best < history[0]["val_nll"] - 0.5
    assert best == pytest.approx(float(true_nll.mean()), abs=0.03)
    assert all(p.requires_grad == (k in HEAD_KEYS) for k, p in net.named_parameters())


def test_missing_point_weights_are_refused_with_their_path(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(FileNotFoundError, match=r"no point weights at .*nothing\.pt"):
        fit_head(tmp_path / "nothing.pt", tmp_path / "out.pt", FAST, log=None)
    code = main(
        ["predictor", "fit-head", "--model", "srnn", "--split", "zara1", "--point", str(tmp_path / "{model}_x.pt")]
    )
    assert code == 2 and "no point weights for srnn/zara1 at" in capsys.readouterr().err
    assert not (tmp_path / "out.pt").exists()


def test_an_existing_output_needs_force(tmp_path: Path, data_dir: Path, capsys: pytest.CaptureFixture) -> None:
    point_checkpoint(tmp_path / "srnn_zara1.pt", data_dir)
    (tmp_path / "g.pt").write_bytes(b"old")
    args = ["predictor", "fit-head", "--model", "srnn", "--split", "zara1", "--point", str(tmp_path / "srnn_zara1.pt")]
    assert main([*args, "--out", str(tmp_path / "g.pt")]) == 2
    assert "exists: pass --force" in capsys.readouterr().err and (tmp_path / "g.pt").read_bytes() == b"old"


def test_the_write_is_atomic(tmp_path: Path, data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A write that fails midway leaves the old file and no partial one."""
    src = point_checkpoint(tmp_path / "srnn_zara1.pt", data_dir)
    dest = tmp_path / "srnn_gaussian_zara1.pt"
    dest.write_bytes(b"old")

    def broken_save(obj: object, fh: object) -> None:
        fh.write(b"partial")  # type: ignore[attr-defined]
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        fit_head(src, dest, FAST, log=None)
    assert dest.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["srnn_gaussian_zara1.pt", "srnn_zara1.pt"]


def test_a_head_on_changed_or_missing_point_weights_is_refused(tmp_path: Path, data_dir: Path) -> None:
    src = point_checkpoint(tmp_path / "srnn_zara1.pt", data_dir)
    dest = tmp_path / "srnn_gaussian_zara1.pt"
    fit_head(src, dest, HeadFitConfig(max_windows=8, max_epochs=2), log=None)
    ck = torch.load(src, weights_only=True)
    ck["state_dict"]["decoder.bias"] += 1e-3
    torch.save(ck, src)
    with pytest.raises(CheckpointError, match="SHA-256"):
        load_predictor(dest)
    src.unlink()
    with pytest.raises(CheckpointError, match="which is missing"):
        load_predictor(dest)


def test_fit_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="patience must be >= 1"):
        HeadFitConfig(patience=0)
    with pytest.raises(ConfigError, match="whiten_floor must lie"):
        HeadFitConfig(whiten_floor=0.0)
    assert math.isfinite(HeadFitConfig().whiten_floor) and np.isclose(HeadFitConfig().whiten_floor, 1e-2)
