"""Structural RNN: shapes, masks, no leakage of the future, learning, checkpoints and errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data import MinMax
from crowdnav_mesrnn.models import ConstantVelocity, get_predictor
from crowdnav_mesrnn.models.architecture import MODEL_TYPES, ModelConfig
from crowdnav_mesrnn.models.learned import CheckpointError, LearnedPredictor, lean_state, load_predictor
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN

SMALL = {"node_embed": 16, "node_hidden": 32, "edge_embed": 8, "edge_hidden": 16}


def make_net(model: str = "mesrnn", seed: int = 0, **kw) -> StructuralRNN:
    torch.manual_seed(seed)
    return StructuralRNN(ModelConfig(model=model, **{**SMALL, **kw})).eval()


def random_batch(b: int = 3, t: int = 20, n: int = 5, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(torch.randn(b, t, n, 2, generator=g) * 0.02, dim=1)
    mask = torch.rand(b, t, n, generator=g) < 0.8
    mask[:, :, 0] = True
    return pos, mask


@pytest.mark.parametrize("model", list(MODEL_TYPES))
def test_shapes(model: str) -> None:
    net = make_net(model)
    pos, mask = random_batch()
    pred, used = net(pos, mask, obs_len=8)
    assert pred.shape == (3, 19, 5, 2) and used.shape == (3, 19, 5)
    assert net.rollout(pos[:, :8], mask[:, :8], 12).shape == (3, 12, 5, 2)


@pytest.mark.parametrize("model", ["mesrnn", "srnn"])
def test_absent_neighbour_changes_nothing(model: str) -> None:
    net = make_net(model)
    pos, mask = random_batch(n=4)
    mask[:, :, 3] = False
    base = net.rollout(pos[:, :8], mask[:, :8], 12)
    moved = pos.clone()
    moved[:, :, 3] += 100.0  # an absent pedestrian anywhere
    out = net.rollout(moved[:, :8], mask[:, :8], 12)
    torch.testing.assert_close(out[:, :, :3], base[:, :, :3])
    # Removing the column entirely gives the same forecasts too (padding is inert).
    out3 = net.rollout(pos[:, :8, :3], mask[:, :8, :3], 12)
    torch.testing.assert_close(out3, base[:, :, :3])


def test_present_neighbour_matters_for_mesrnn_not_vlstm() -> None:
    pos, mask = random_batch(n=3)
    mask[:] = True
    moved = pos.clone()
    moved[:, :, 2] += 0.5
    for model, should_change in (("mesrnn", True), ("vlstm", False)):
        net = make_net(model)
        a = net.rollout(pos[:, :8], mask[:, :8], 12)[:, :, 0]
        b = net.rollout(moved[:, :8], mask[:, :8], 12)[:, :, 0]
        assert (not torch.allclose(a, b)) == should_change, model


def test_rollout_never_reads_the_future() -> None:
    net = make_net("mesrnn")
    pos, mask = random_batch()
    base, _ = net(pos, mask, obs_len=8, teacher_forcing=False)
    noisy = pos.clone()
    noisy[:, 8:] += torch.randn_like(noisy[:, 8:]) * 10
    flipped = mask.clone()
    flipped[:, 8:] = ~flipped[:, 8:]
    out, _ = net(noisy, flipped, obs_len=8, teacher_forcing=False)
    torch.testing.assert_close(out, base)
    # With teacher forcing the future is read (the check above could fail).
    tf_a, _ = net(pos, mask, obs_len=8, teacher_forcing=True)
    tf_b, _ = net(noisy, mask, obs_len=8, teacher_forcing=True)
    assert not torch.allclose(tf_a[:, 8:], tf_b[:, 8:])


def test_predictor_forecast_interface_and_future_independence() -> None:
    net = make_net("mesrnn")
    norm = MinMax((0.0, 0.0), (10.0, 10.0))
    pred = LearnedPredictor(net, norm)
    rng = np.random.default_rng(0)
    hist = rng.uniform(2, 8, size=(8, 4, 2)).astype(np.float32)
    mask = np.ones((8, 4), bool)
    mask[-1, 3] = False
    out = pred.forecast(hist, mask)
    assert out.shape == (4, 12, 2) and out.dtype == np.float32
    np.testing.assert_allclose(out[3], np.repeat(hist[-2, 3][None], 12, 0))
    with pytest.raises(ValueError, match="history must have shape"):
        pred.forecast(hist[:5], mask[:5])
    bad = hist.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        pred.forecast(bad, mask)


def test_constant_velocity() -> None:
    hist = np.cumsum(np.full((8, 2, 2), 0.5, np.float32), axis=0)
    out = ConstantVelocity().forecast(hist, np.ones((8, 2), bool))
    np.testing.assert_allclose(out[:, -1], hist[-1] + 12 * 0.5)


def test_overfitting_one_batch_decreases_loss() -> None:
    from crowdnav_mesrnn.training.trainer import masked_loss

    net = make_net("mesrnn").train()
    pos, mask = random_batch(b=4, n=4, seed=1)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        pred, used = net(pos, mask, 8, teacher_forcing=True)
        loss = masked_loss(pred, used, pos, mask)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="valid models: mesrnn, srnn, vlstm"):
        ModelConfig(model="sgan")
    with pytest.raises(ConfigError, match="valid keys"):
        ModelConfig.from_dict({"model": "srnn", "hiden": 3})
    with pytest.raises(ValueError, match="valid: cv, cv_gaussian, mesrnn, srnn, vlstm"):
        get_predictor("lstm")
    with pytest.raises(ValueError, match="valid splits"):
        get_predictor("mesrnn", "zara3")


def test_checkpoint_mismatch_errors(tmp_path: Path) -> None:
    net = make_net("srnn")
    ck = {
        "model_config": net.cfg.to_dict(),
        "state_dict": lean_state(net),
        "norm": MinMax((0.0, 0.0), (1.0, 1.0)).to_dict(),
        "train_config": {"split": "zara1"},
    }
    path = tmp_path / "a.pt"
    torch.save(ck, path)
    assert load_predictor(path, model="srnn", split="zara1").name == "srnn"
    with pytest.raises(CheckpointError, match="holds a 'srnn' model, not 'mesrnn'"):
        load_predictor(path, model="mesrnn")
    with pytest.raises(CheckpointError, match="trained for split 'zara1', not 'eth'"):
        load_predictor(path, split="eth")
    ck["model_config"] = {**ck["model_config"], "node_hidden": 64}
    torch.save(ck, path)
    with pytest.raises(CheckpointError, match="do not match the config"):
        load_predictor(path)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="unreadable"):
        load_predictor(path)


@pytest.mark.parametrize("model", list(MODEL_TYPES))
def test_online_forecaster_matches_from_scratch_forecast(model: str) -> None:
    pred = LearnedPredictor(make_net(model), MinMax((0.0, 0.0), (10.0, 10.0)))
    rng = np.random.default_rng(1)
    hist = np.cumsum(rng.normal(0.3, 0.1, size=(8, 5, 2)), axis=0).astype(np.float32) + 2
    mask = rng.uniform(size=(8, 5)) < 0.8
    mask[-1, :2] = True
    online = pred.online(5)
    for t in range(8):
        online.observe(hist[t], mask[t])
    np.testing.assert_allclose(online.forecast(), pred.forecast(hist, mask), rtol=1e-5, atol=1e-5)


def test_cv_residual_starts_as_constant_velocity() -> None:
    net = make_net("mesrnn", offset="cv_residual")
    pos, mask = random_batch(n=3)
    mask[:] = True
    out = net.rollout(pos[:, :8], mask[:, :8], 12)
    vel = pos[:, 7] - pos[:, 6]
    want = pos[:, 7].unsqueeze(1) + torch.arange(1, 13).view(1, 12, 1, 1) * vel.unsqueeze(1)
    torch.testing.assert_close(out, want, rtol=1e-5, atol=1e-5)


def test_fit_input_scales_gives_unit_rms_and_is_saved() -> None:
    net = make_net("mesrnn", standardise=True, node_input="velocity")
    pos, mask = random_batch(b=4, n=6)
    net.fit_input_scales(pos, mask)
    assert torch.all(net.edge_scale != 1.0) and torch.all(net.node_scale != 1.0)
    assert "edge_scale" in net.state_dict() and "node_scale" in net.state_dict()


def test_online_forecaster_carries_state_and_ignores_absent_slots() -> None:
    """Many steps with pedestrians coming and going: the subset computation equals the full batch."""
    pred = LearnedPredictor(make_net("mesrnn"), MinMax((0.0, 0.0), (10.0, 10.0)))
    rng = np.random.default_rng(2)
    t_len, n = 14, 7
    pos = (np.cumsum(rng.normal(0.2, 0.1, size=(t_len, n, 2)), axis=0) + 2).astype(np.float32)
    mask = rng.uniform(size=(t_len, n)) < 0.6
    online = pred.online(n)
    for t in range(t_len):
        online.observe(pos[t], mask[t])
    # Reference: the full structural RNN over all slots for all steps, then the same rollout.
    net = pred.net
    normed = torch.where(torch.from_numpy(mask)[..., None], pred.norm.normalise(torch.from_numpy(pos)), 0.0)
    with torch.no_grad():
        full = net.rollout(normed[None], torch.from_numpy(mask)[None], 12)[0]
    want = pred.norm.denormalise(full).permute(1, 0, 2).numpy()
    got = online.forecast()
    live = mask[-1]
    np.testing.assert_allclose(got[live], want[live], rtol=1e-5, atol=1e-5)


def test_online_forecaster_keeps_no_view_of_the_callers_arrays() -> None:
    """A tracker refilling one position and one presence buffer in place every frame gets the forecasts of fresh
    arrays (the presence was kept as a view of the caller's array: a later refill rewrote the past frame's mask)."""
    pred = LearnedPredictor(make_net("mesrnn"), MinMax((0.0, 0.0), (10.0, 10.0)))
    rng = np.random.default_rng(4)
    t_len, n = 8, 6
    pos = (np.cumsum(rng.normal(0.2, 0.1, size=(t_len, n, 2)), axis=0) + 2).astype(np.float32)
    mask = np.ones((t_len, n), bool)
    mask[:5, 3] = False  # enters late
    mask[6, 5] = False  # absent at t - 1 only
    mask[5, 2] = False  # absent at t - 2 only
    fresh, reused = pred.online(n), pred.online(n)
    buf_p, buf_m = np.zeros((n, 2), np.float32), np.zeros(n, bool)
    for t in range(t_len):
        fresh.observe(pos[t].copy(), mask[t].copy())
        buf_p[:], buf_m[:] = pos[t], mask[t]
        reused.observe(buf_p, buf_m)
    np.testing.assert_array_equal(reused.forecast(), fresh.forecast())
    np.testing.assert_allclose(fresh.forecast(), pred.forecast(pos, mask), rtol=0, atol=1e-4)
