"""The fast structural RNN (batched gate inputs, live rows only, sigmoid-based tanh) equals the plain
definition (``crowdnav_mesrnn.models.reference``), and the shipped predictors forecast what they did
before it (``fixtures/shipped_forecasts.npz``, made with the first implementation)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from crowdnav_mesrnn import load_pretrained
from crowdnav_mesrnn.models.architecture import MODEL_TYPES, ModelConfig
from crowdnav_mesrnn.models.reference import reference_forward, reference_rollout, reference_step
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "shipped_forecasts.npz"
SMALL = {"node_embed": 16, "node_hidden": 24, "edge_embed": 8, "edge_hidden": 12}
VARIANTS = [
    {},
    {"aggregate": "mean", "node_input": "velocity", "offset": "cv_residual", "feature_scale": 0.5},
]


def random_net(model: str, seed: int = 0, **kw) -> StructuralRNN:
    torch.manual_seed(seed)
    net = StructuralRNN(ModelConfig(model=model, **{**SMALL, **kw}))
    with torch.no_grad():
        for p in net.parameters():  # non-zero everywhere (the residual decoder starts at zero)
            p.uniform_(-0.5, 0.5)
        net.edge_scale.uniform_(0.5, 2.0)
        net.node_scale.uniform_(0.5, 2.0)
    return net


def random_batch(b: int = 3, t: int = 20, n: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random walks with pedestrians entering and leaving, one pedestrian never present, one empty step."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(torch.randn(b, t, n, 2, generator=g) * 0.05, dim=1) + torch.rand(b, 1, n, 2, generator=g)
    mask = torch.rand(b, t, n, generator=g) < 0.7
    mask[:, :, 0] = True
    mask[:, :, -1] = False
    mask[1, 4] = False
    return torch.where(mask.unsqueeze(-1), pos, torch.full_like(pos, 7.0)), mask


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("model", list(MODEL_TYPES))
@pytest.mark.parametrize("teacher_forcing", [True, False])
def test_forward_and_gradients_equal_the_reference(model: str, variant: dict, teacher_forcing: bool) -> None:
    net = random_net(model, **variant).train()
    pos, mask = random_batch()
    pred, used = net(pos, mask, 8, teacher_forcing=teacher_forcing)
    ref, ref_used = reference_forward(net, pos, mask, 8, teacher_forcing=teacher_forcing)
    torch.testing.assert_close(pred, ref, rtol=1e-5, atol=1e-5)
    assert torch.equal(used, ref_used)
    weights = torch.rand_like(pred)
    grads = torch.autograd.grad((pred * weights).sum(), list(net.parameters()))
    ref_grads = torch.autograd.grad((ref * weights).sum(), list(net.parameters()))
    for (name, _), a, b in zip(net.named_parameters(), grads, ref_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4, msg=name)


@pytest.mark.parametrize("model", list(MODEL_TYPES))
def test_rollout_and_single_step_equal_the_reference(model: str) -> None:
    net = random_net(model, seed=1, **VARIANTS[1]).eval()
    pos, mask = random_batch(seed=1)
    with torch.no_grad():
        torch.testing.assert_close(
            net.rollout(pos[:, :8], mask[:, :8], 12), reference_rollout(net, pos[:, :8], mask[:, :8], 12)
        )
        state = {k: torch.randn_like(v) for k, v in net.init_state(3 * 6).items()}
        p3 = tuple(torch.where(mask[:, t, :, None], pos[:, t], 0.0) for t in (5, 4, 3))
        m3 = tuple(mask[:, t] for t in (5, 4, 3))
        got, got_state = net.step(p3, m3, state)
        want, want_state = reference_step(net, p3, m3, state)
    torch.testing.assert_close(got, want)
    for key, value in want_state.items():
        torch.testing.assert_close(got_state[key], value, msg=key)
    # Rows absent at the step keep their state exactly.
    absent = ~m3[0].reshape(-1)
    torch.testing.assert_close(got_state["node_h"][absent], state["node_h"][absent], rtol=0, atol=0)


def test_bf16_autocast_runs_close_to_fp32() -> None:
    net = random_net("mesrnn", seed=2).train()
    pos, mask = random_batch(seed=2)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        pred, _ = net(pos, mask, 8, teacher_forcing=False)
    assert pred.dtype == torch.float32
    ref, _ = net(pos, mask, 8, teacher_forcing=False)
    assert (pred - ref).abs().max() < 0.1 * ref.abs().max()
    (pred.sum()).backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


@pytest.mark.parametrize("model", ["mesrnn", "srnn", "vlstm"])
def test_shipped_zara1_forecasts_unchanged(model: str) -> None:
    """Same forecasts as the first implementation, to float32 rounding over a 20-step recurrence
    (0.1 mm; padding the same history with absent pedestrians moved the first implementation's own
    forecasts by 0.008 mm)."""
    data = np.load(FIXTURE)
    pred = load_pretrained(model, "zara1")
    np.testing.assert_allclose(
        pred.forecast(data["history"], data["history_mask"]), data[f"{model}_forecast"], rtol=0, atol=1e-4
    )
    seq, seq_mask = data["sequence"], data["sequence_mask"]
    online = pred.online(seq.shape[1])
    got = []
    for t in range(seq.shape[0]):
        online.observe(seq[t], seq_mask[t])
        if t in (7, 13):
            got.append(online.forecast())
    np.testing.assert_allclose(np.stack(got), data[f"{model}_online"], rtol=0, atol=1e-4)
