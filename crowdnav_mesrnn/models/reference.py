"""The structural RNN as first written: one step at a time, every row computed, absent rows kept by
``torch.where``, ``torch.tanh``, the concatenated LSTM inputs.

Kept as the plain definition that the fast path of :class:`~crowdnav_mesrnn.models.structural_rnn.StructuralRNN`
is tested against (``tests/models/test_fast_path.py``) and timed against (``benchmarks/predictor_speed.py``).
It uses the same parameters, so any network can be run both ways.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from crowdnav_mesrnn.graph.metapaths import metapath_features_step
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN


def reference_features(net: StructuralRNN, p: tuple, m: tuple) -> torch.Tensor | None:
    """``(K, B*N, 2)`` edge features at one step (each input ``(B, N, ·)``)."""
    if not net.types:
        return None
    feats = metapath_features_step(p[0], p[1], p[2], m[0], m[1], m[2], net.types)
    if net.cfg.aggregate == "mean":
        n_t = m[0].sum(-1, keepdim=True).unsqueeze(-1).to(p[0].dtype)
        n_prev = m[1].sum(-1, keepdim=True).unsqueeze(-1).to(p[0].dtype)
        nb = (n_t - 1).clamp(min=1)
        scale = {"S": nb, "ST": nb, "SS": nb * (n_t - 2).clamp(min=1), "TS": (n_prev - 1).clamp(min=1)}
        feats = {k: v / scale[k] if k in scale else v for k, v in feats.items()}
    stacked = torch.stack([feats[t] for t in net.types], dim=0)
    if net.cfg.feature_scale != 1.0:
        stacked = stacked * net.cfg.feature_scale
    return stacked.flatten(1, 2) * net.edge_scale[: len(net.types)]


def reference_step(net: StructuralRNN, p: tuple, m: tuple, state: dict) -> tuple[torch.Tensor, dict]:
    b, n, _ = p[0].shape
    present = m[0].reshape(b * n, 1)
    vel = (p[0] - p[1]) * (m[0] & m[1]).unsqueeze(-1).to(p[0].dtype)
    node_in = vel if net.cfg.node_input == "velocity" else p[0]
    x_node = net.drop(torch.tanh(net.node_embed(node_in.reshape(b * n, 2) * net.node_scale)))
    edge = reference_features(net, p, m)
    new = dict(state)
    if edge is not None:
        e = net.drop(torch.tanh(torch.baddbmm(net.edge_embed_b, edge, net.edge_embed_w)))
        eh, ec = net.edge_cell(e, state["edge_h"], state["edge_c"])
        new["edge_h"] = torch.where(present.unsqueeze(0), eh, state["edge_h"])
        new["edge_c"] = torch.where(present.unsqueeze(0), ec, state["edge_c"])
        x_node = torch.cat([x_node, new["edge_h"].permute(1, 0, 2).reshape(b * n, -1)], dim=-1)
    nh, nc = net.node_cell(x_node, (state["node_h"], state["node_c"]))
    new["node_h"] = torch.where(present, nh, state["node_h"])
    new["node_c"] = torch.where(present, nc, state["node_c"])
    offset = torch.tanh(net.decoder(new["node_h"])).reshape(b, n, 2)
    if net.cfg.offset == "cv_residual":
        offset = offset + vel
    return p[0] + offset, new


def reference_forward(
    net: StructuralRNN,
    positions: torch.Tensor,
    mask: torch.Tensor,
    obs_len: int,
    teacher_forcing: bool = True,
    raws: list[torch.Tensor] | None = None,
    feed: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``StructuralRNN.forward`` as first written: ``(B, T−1, N, 2)`` predictions and the masks used.

    With the gaussian head, ``raws`` (if given) receives each step's raw ``(σx, σy, ρ)`` ``(B, N, 3)`` (the head
    applied to the new node state), and ``feed`` (without teacher forcing) replaces every prediction from the
    last observed step on by ``feed(mean, raw)`` before it is fed back, as ``StructuralRNN.scan_distribution``.
    """
    b, t_len, n, _ = positions.shape
    state = net.init_state(b * n, positions.device)
    zeros_p = positions.new_zeros(b, n, 2)
    zeros_m = torch.zeros(b, n, dtype=torch.bool, device=positions.device)
    hist_p, hist_m = [zeros_p, zeros_p], [zeros_m, zeros_m]
    roll_mask = mask[:, obs_len - 1]
    preds, used = [], []
    pred = zeros_p
    for t in range(t_len - 1):
        if t < obs_len or teacher_forcing:
            p_t, m_t = positions[:, t], mask[:, t]
        else:
            p_t, m_t = pred, roll_mask
        p_t = torch.where(m_t.unsqueeze(-1), p_t, zeros_p)
        pred, state = reference_step(net, (p_t, hist_p[0], hist_p[1]), (m_t, hist_m[0], hist_m[1]), state)
        if net.gaussian:
            ahead = 0 if (t < obs_len or teacher_forcing) else t - obs_len + 1  # steps after the last observed input
            raw = (net.scale_head(state["node_h"]) + net.step_bias[min(ahead, len(net.step_bias) - 1)]).reshape(b, n, 3)
            if raws is not None:
                raws.append(raw)
            if feed is not None and not teacher_forcing and t >= obs_len - 1:
                pred = feed(pred, raw)
        preds.append(pred)
        used.append(m_t)
        hist_p, hist_m = [p_t, hist_p[0]], [m_t, hist_m[0]]
    return torch.stack(preds, dim=1), torch.stack(used, dim=1)


def reference_rollout(net: StructuralRNN, obs_p: torch.Tensor, obs_m: torch.Tensor, pred_len: int) -> torch.Tensor:
    b, obs_len, n, _ = obs_p.shape
    pos = torch.cat([obs_p, obs_p.new_zeros(b, pred_len, n, 2)], 1)
    mask = torch.cat([obs_m.bool(), torch.zeros(b, pred_len, n, dtype=torch.bool)], 1)
    return reference_forward(net, pos, mask, obs_len, teacher_forcing=False)[0][:, obs_len - 1 :]
