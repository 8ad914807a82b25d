"""One structural RNN, three models: MESRNN {S,T,SS,ST,TS,TT}, SRNN {S,T}, VLSTM {}.

Per meta-path type an EdgeRNN (linear embedding + tanh + dropout, LSTM cell) reads the summed
feature of that type; the NodeRNN reads an embedding of the node's own position concatenated with
the edge hidden states and decodes an offset (linear + tanh); next position = current + offset.
All pedestrians of all windows step together; an absent pedestrian neither updates its hidden
states nor influences its neighbours (its features and its contribution to theirs are masked).

The architecture is :mod:`crowdnav_mesrnn.models.architecture`, the LSTM arithmetic
:mod:`crowdnav_mesrnn.models.recurrence`, and the online (one frame at a time) path
:mod:`crowdnav_mesrnn.models.online`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from crowdnav_mesrnn._deprecated import moved_attributes
from crowdnav_mesrnn.data.constants import PRED_LEN
from crowdnav_mesrnn.graph.metapaths import stacked_features_step
from crowdnav_mesrnn.models.gaussian import params_from_raw, raw_sigma_init
from crowdnav_mesrnn.models.gaussian import sample as gaussian_sample
from crowdnav_mesrnn.models.online import OnlineInference
from crowdnav_mesrnn.models.recurrence import GroupedLSTMCell, LiveRows, gate_scale, lstm_pointwise, tanh_from_doubled

if TYPE_CHECKING:
    from crowdnav_mesrnn.models.architecture import ModelConfig


class StructuralRNN(OnlineInference, nn.Module):
    """The structural RNN over a spatio-temporal graph; positions in normalised units.

    Implementation notes (the arithmetic is that of the module docstring; only its order changes):
    the gate inputs of every step whose inputs are known (all observed steps; all steps with teacher
    forcing) are computed in one batched pass before the recurrence — meta-path features, embeddings
    and the input half of every LSTM — so the loop over steps only does the recurrent matmuls (one
    batched matmul for all edge types, one for the node) and the pointwise updates; only pedestrians
    present at a step are computed; ``tanh`` is evaluated as ``2 σ(2z) − 1``.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.types = cfg.types
        k = len(self.types)
        self.drop = nn.Dropout(cfg.dropout)
        if k:
            bound = 1.0 / math.sqrt(2)
            self.edge_embed_w = nn.Parameter(torch.empty(k, 2, cfg.edge_embed).uniform_(-bound, bound))
            self.edge_embed_b = nn.Parameter(torch.empty(k, 1, cfg.edge_embed).uniform_(-bound, bound))
            self.edge_cell = GroupedLSTMCell(k, cfg.edge_embed, cfg.edge_hidden)
        # Input scales (1 unless fitted by :meth:`fit_input_scales`); buffers, so saved with the weights.
        self.register_buffer("edge_scale", torch.ones(max(k, 1), 1, 2))
        self.register_buffer("node_scale", torch.ones(2))
        self.node_embed = nn.Linear(2, cfg.node_embed)
        self.node_cell = nn.LSTMCell(cfg.node_embed + k * cfg.edge_hidden, cfg.node_hidden)
        self.decoder = nn.Linear(cfg.node_hidden, 2)
        if cfg.offset == "cv_residual":
            nn.init.zeros_(self.decoder.weight)
            nn.init.zeros_(self.decoder.bias)
        self.gaussian = cfg.head == "gaussian"
        if self.gaussian:
            # raw (σx, σy, ρ) of the next position; starts at σ = SIGMA_INIT, ρ = 0 for every input
            self.scale_head = nn.Linear(cfg.node_hidden, 3)
            nn.init.zeros_(self.scale_head.weight)
            with torch.no_grad():
                self.scale_head.bias.copy_(torch.tensor([raw_sigma_init(), raw_sigma_init(), 0.0]))
            # added to the raw output by how many steps ahead of the last observed input the prediction is
            # (0: the step after an observation; k: the k-th step fed with the model's own prediction)
            self.step_bias = nn.Parameter(torch.zeros(PRED_LEN, 3))
        self._prepared: tuple[tuple[int, ...], dict[str, torch.Tensor]] | None = None
        self._online: tuple[tuple[int, ...], dict[str, Any]] | None = None

    def __getstate__(self) -> dict[str, Any]:
        # the cached derived weights (one of them an opaque oneDNN tensor) are not part of the network: copies and
        # pickles rebuild them on first use
        state = self.__dict__.copy()
        state["_prepared"] = None
        state["_online"] = None
        return state

    # ------------------------------------------------------------------ state
    def init_state(self, rows: int, device: torch.device | None = None) -> dict[str, torch.Tensor]:
        """Zero hidden states for ``rows`` pedestrians (flattened batch)."""
        k, cfg = len(self.types), self.cfg
        dev = device or self.decoder.weight.device
        return {
            "node_h": torch.zeros(rows, cfg.node_hidden, device=dev),
            "node_c": torch.zeros(rows, cfg.node_hidden, device=dev),
            "edge_h": torch.zeros(k, rows, cfg.edge_hidden, device=dev),
            "edge_c": torch.zeros(k, rows, cfg.edge_hidden, device=dev),
        }

    # ---------------------------------------------------------------- weights
    def _weights(self) -> dict[str, torch.Tensor]:
        """The parameters rearranged for the fast path (input/recurrent halves, doubled ``tanh`` inputs).

        Differentiable functions of the parameters; cached while gradients are off and no parameter changed.
        """
        caching = not torch.is_grad_enabled()
        if caching:
            key = tuple(v for p in self.parameters() for v in (p.data_ptr(), p._version))
            if self._prepared is not None and self._prepared[0] == key:
                return self._prepared[1]
        cfg, k = self.cfg, len(self.types)
        cell = self.node_cell
        gs = gate_scale(cfg.node_hidden, cell.weight_ih)[:, None]
        w_ih, w_hh = cell.weight_ih * gs, cell.weight_hh * gs
        ne = cfg.node_embed
        out = {
            "node_embed_w": (self.node_embed.weight * 2.0).t(),
            "node_embed_b": self.node_embed.bias * 2.0,
            "node_x_w": w_ih[:, :ne].t(),
            "node_b": (cell.bias_ih + cell.bias_hh) * gs[:, 0],
            "node_rec_w": torch.cat([w_ih[:, ne:], w_hh], dim=1).t(),
        }
        if k:
            gse = gate_scale(cfg.edge_hidden, self.edge_cell.weight)
            w = self.edge_cell.weight * gse
            out |= {
                "edge_embed_w": self.edge_embed_w * 2.0,
                "edge_embed_b": self.edge_embed_b * 2.0,
                "edge_x_w": w[:, : cfg.edge_embed],
                "edge_h_w": w[:, cfg.edge_embed :],
                "edge_b": self.edge_cell.bias * gse,
            }
        if caching:
            out = {name: v.contiguous() for name, v in out.items()}
            self._prepared = (key, out)
        return out

    def head_parameters(self) -> list[nn.Parameter]:
        """The distribution head's parameters (empty with the point head)."""
        return [*self.scale_head.parameters(), self.step_bias] if self.gaussian else []

    def _head_linear(self, node_h: torch.Tensor) -> torch.Tensor:
        return nn.functional.linear(node_h, self.scale_head.weight, self.scale_head.bias)

    def _step_bias(self, ahead: int) -> torch.Tensor:
        """``(3,)`` the head's bias for a prediction ``ahead`` steps after the last observed input (the last row
        serves every longer horizon)."""
        return self.step_bias[min(ahead, len(self.step_bias) - 1)]

    def head_raw(self, node_h: torch.Tensor, ahead: int = 0) -> torch.Tensor:
        """The distribution head's raw ``(σx, σy, ρ)`` ``(..., 3)`` from node states ``(..., node_hidden)`` of a
        prediction ``ahead`` steps after the last observed input."""
        return self._head_linear(node_h) + self._step_bias(ahead)

    # --------------------------------------------------------------- features
    def _features(
        self, p: tuple[torch.Tensor, ...], m: tuple[torch.Tensor, ...] | None
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """Scaled edge features ``(K, ..., N, 2)`` (``None`` without edge types) and the velocity
        ``(..., N, 2)``, from positions/masks at t, t−1, t−2 (each ``(..., N, ·)``); ``m=None`` when every
        pedestrian is present at all three steps (the same values with fewer operations)."""
        dt = p[0].dtype
        k = len(self.types)
        if not k:
            return None, p[0] - p[1] if m is None else (p[0] - p[1]) * (m[0] & m[1]).unsqueeze(-1).to(dt)
        if m is None:
            feats, vel = stacked_features_step(p[0], p[1], p[2], None, None, None, self.types)
            if self.cfg.aggregate == "mean":
                n = p[0].shape[-2]
                nb = float(max(n - 1, 1))
                div_d = {"S": nb, "ST": nb, "SS": nb * max(n - 2, 1), "TS": nb}
                feats = torch.stack([f / div_d[t] if t in div_d else f for t, f in zip(self.types, feats, strict=True)])
        else:
            w = [x.to(dt).unsqueeze(-1) for x in m]  # (..., N, 1)
            feats, vel = stacked_features_step(p[0], p[1], p[2], w[0], w[1], w[2], self.types)
            if self.cfg.aggregate == "mean":
                n_t = w[0].sum(-2, keepdim=True)  # (..., 1, 1)
                nb_t = (n_t - 1).clamp(min=1)
                div = {"S": nb_t, "ST": nb_t, "SS": nb_t * (n_t - 2).clamp(min=1)}
                if "TS" in self.types:
                    div["TS"] = (w[1].sum(-2, keepdim=True) - 1).clamp(min=1)
                feats = torch.stack([f / div[t] if t in div else f for t, f in zip(self.types, feats, strict=True)])
        if self.cfg.feature_scale != 1.0:
            feats = feats * self.cfg.feature_scale
        return feats * self.edge_scale[:k].reshape(k, *([1] * (feats.dim() - 2)), 2), vel

    @torch.no_grad()
    def fit_input_scales(self, positions: torch.Tensor, mask: torch.Tensor) -> None:
        """Set the input scales to 1 / RMS of each edge feature type (and the node input) over present
        pedestrians of a ``(B, T, N, 2)`` batch of training windows (normalised units)."""
        self.edge_scale.fill_(1.0)
        self.node_scale.fill_(1.0)
        m = mask.bool()
        p1 = torch.cat([torch.zeros_like(positions[:, :1]), positions[:, :-1]], 1)
        m1 = torch.cat([torch.zeros_like(m[:, :1]), m[:, :-1]], 1)
        p2 = torch.cat([torch.zeros_like(positions[:, :2]), positions[:, :-2]], 1)
        m2 = torch.cat([torch.zeros_like(m[:, :2]), m[:, :-2]], 1)
        if self.types:
            feats, _ = self._features((positions, p1, p2), (m, m1, m2))
            assert feats is not None
            sel = feats.reshape(len(self.types), -1, 2)[:, m.reshape(-1)]  # (K, present rows, 2)
            rms = sel.pow(2).mean(1, keepdim=True).sqrt().clamp(min=1e-6)
            self.edge_scale[: len(self.types)] = 1.0 / rms
        if self.cfg.node_input == "velocity":
            both = m & m1
            vel = (positions - p1)[both]
        else:
            vel = positions[m]
        self.node_scale.copy_(1.0 / vel.pow(2).mean(0).sqrt().clamp(min=1e-6))

    # --------------------------------------------------------------- the step
    def _gate_inputs(
        self,
        w: dict[str, torch.Tensor],
        p: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        m: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
        rows: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """Input halves of the node and edge gates for ``rows`` of the flattened ``(..., N)`` grid
        (``None``: all), from positions/masks at t, t−1, t−2 (each ``(..., N, ·)``; ``m=None``: everyone present).

        Returns ``node (P, 4 node_hidden)``, ``edge (K, P, 4 edge_hidden)`` or ``None``, and the
        velocity ``(..., N, 2)``.
        """
        feats, vel = self._features(p, m)
        node_in = (vel if self.cfg.node_input == "velocity" else p[0]).reshape(-1, 2)
        if rows is not None:
            node_in = node_in.index_select(0, rows)
        x = tanh_from_doubled(torch.addmm(w["node_embed_b"], node_in * self.node_scale, w["node_embed_w"]))
        node = torch.addmm(w["node_b"], self.drop(x), w["node_x_w"])
        if feats is None:
            return node, None, vel
        f = feats.reshape(len(self.types), -1, 2)
        if rows is not None:
            f = f.index_select(1, rows)
        e = tanh_from_doubled(torch.baddbmm(w["edge_embed_b"], f, w["edge_embed_w"]))
        return node, torch.baddbmm(w["edge_b"], self.drop(e), w["edge_x_w"]), vel

    def _decode(self, h: torch.Tensor) -> torch.Tensor:
        """``(P, 2)`` offsets, or with the gaussian head ``(P, 5)``: the offset (the mean's) then the head's raw
        ``(σx, σy, ρ)``; always float32 (under bf16 autocast too: they are added to positions)."""
        if torch.is_autocast_enabled("cpu"):
            with torch.autocast("cpu", enabled=False):
                return self._decode_fp32(h.float())
        return self._decode_fp32(h)

    def _decode_fp32(self, h: torch.Tensor) -> torch.Tensor:
        offset = torch.tanh(nn.functional.linear(h, self.decoder.weight, self.decoder.bias))
        if not self.gaussian:
            return offset
        return torch.cat([offset, self._head_linear(h.detach() if self.cfg.scale_detach else h)], dim=-1)

    def _recurrent(
        self,
        w: dict[str, torch.Tensor],
        node_x: torch.Tensor,
        edge_x: torch.Tensor | None,
        sub: dict[str, torch.Tensor],
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Recurrent half of one step for ``P`` rows: new states and decoder offsets ``(P, 2)``."""
        new: dict[str, torch.Tensor] = {}
        if edge_x is not None:
            gates = torch.baddbmm(edge_x, sub["edge_h"], w["edge_h_w"])  # all edge types in one matmul
            new["edge_h"], new["edge_c"] = lstm_pointwise(gates, sub["edge_c"])
            z = torch.cat([*new["edge_h"].unbind(0), sub["node_h"]], dim=1)
        else:
            z = sub["node_h"]
        new["node_h"], new["node_c"] = lstm_pointwise(torch.addmm(node_x, z, w["node_rec_w"]), sub["node_c"])
        return new, self._decode(new["node_h"])

    def _advance(
        self,
        w: dict[str, torch.Tensor],
        live: LiveRows,
        rows: torch.Tensor | None,
        node_x: torch.Tensor,
        edge_x: torch.Tensor | None,
    ) -> torch.Tensor:
        """Recurrent half of one step for ``rows``; returns every row's decoder offset ``(R, 2)``."""
        sub = live.select(rows)
        new, offsets = self._recurrent(w, node_x, edge_x, sub)
        sub.update(new)
        return live.offsets(offsets)

    def scan(
        self,
        known_p: torch.Tensor,
        known_m: torch.Tensor,
        history_p: tuple[torch.Tensor, torch.Tensor],
        history_m: tuple[torch.Tensor, torch.Tensor],
        state: dict[str, torch.Tensor],
        free_steps: int = 0,
        roll_mask: torch.Tensor | None = None,
        first_pred: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Run ``L`` steps with given inputs, then ``free_steps`` steps fed with the model's own predictions
        (the means, with the gaussian head); see :meth:`scan_distribution` for the arguments and the head's output.

        Returns:
            ``(L + free_steps, B, N, 2)`` predictions of the next positions, the presence used at each
            step ``(L + free_steps, B, N)``, and the new state (rows absent at a step keep theirs).
        """
        preds, _, used, new = self.scan_distribution(
            known_p, known_m, history_p, history_m, state, free_steps, roll_mask, first_pred
        )
        return preds, used, new

    def scan_distribution(
        self,
        known_p: torch.Tensor,
        known_m: torch.Tensor,
        history_p: tuple[torch.Tensor, torch.Tensor],
        history_m: tuple[torch.Tensor, torch.Tensor],
        state: dict[str, torch.Tensor],
        free_steps: int = 0,
        roll_mask: torch.Tensor | None = None,
        first_pred: torch.Tensor | None = None,
        feed: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, dict[str, torch.Tensor]]:
        """Run ``L`` steps with given inputs, then ``free_steps`` steps fed with the model's own predictions.

        Args:
            known_p: ``(L, B, N, 2)`` normalised inputs (0 where absent); ``L`` may be 0.
            known_m: ``(L, B, N)`` bool presence.
            history_p: positions at the two steps before the first one, ``(t−1, t−2)``, each ``(B, N, 2)``.
            history_m: their presence, each ``(B, N)`` bool.
            state: hidden states of the ``B*N`` rows (see :meth:`init_state`).
            free_steps: steps after the known ones; their input is the previous prediction for the
                pedestrians of ``roll_mask`` (the others are absent).
            roll_mask: ``(B, N)`` bool, who is rolled out (needed when ``free_steps > 0``).
            first_pred: ``(B, N, 2)`` the prediction fed to the first free step when ``L == 0``.
            feed: with the gaussian head, ``(mean (B, N, 2), raw (B, N, 3)) -> (B, N, 2)``: what replaces (is fed
                back and returned) the last known step's prediction when ``free_steps > 0`` and every free step's,
                e.g. a sample drawn from the step's Gaussian; None keeps the means.

        Returns:
            ``(L + free_steps, B, N, 2)`` predictions of the next positions (the means, or what ``feed`` made
            of them), the gaussian head's raw ``(σx, σy, ρ)`` at each step ``(L + free_steps, B, N, 3)`` (None
            with the point head; :func:`crowdnav_mesrnn.models.gaussian.params_from_raw` turns them into scales
            and correlations), the presence used at each step ``(L + free_steps, B, N)``, and the new state
            (rows absent at a step keep theirs).
        """
        n_known, b, n = known_m.shape
        r = b * n
        w = self._weights()
        live = LiveRows(state, self._decode)
        residual = self.cfg.offset == "cv_residual"
        gaussian = self.gaussian
        preds: list[torch.Tensor] = []
        raws: list[torch.Tensor] = []
        used: list[torch.Tensor] = []
        h_p, h_m = history_p, history_m
        if n_known:
            p_all = torch.cat([h_p[1][None], h_p[0][None], known_p], 0)
            m_all = torch.cat([h_m[1][None], h_m[0][None], known_m], 0)
            p3 = (p_all[2:], p_all[1:-1], p_all[:-2])
            m3 = (m_all[2:], m_all[1:-1], m_all[:-2])
            idx = torch.nonzero(known_m.reshape(-1)).flatten()
            counts = known_m.reshape(n_known, r).sum(1).tolist()
            node_x, edge_x, vel = self._gate_inputs(w, p3, m3, None if len(idx) == n_known * r else idx)
            # split, not slices: the backward of a split is one concatenation, that of L slices L zero-filled copies
            node_xs = node_x.split(counts)
            edge_xs = [None] * n_known if edge_x is None else edge_x.split(counts, dim=1)
            rows_all = idx.split(counts)
            for t, count in enumerate(counts):
                rows = None if count == r else rows_all[t] - t * r
                offset = self._advance(w, live, rows, node_xs[t], edge_xs[t]).view(b, n, -1)
                if gaussian:
                    raws.append(offset[..., 2:] + self._step_bias(0))
                    offset = offset[..., :2]
                preds.append(known_p[t] + offset + vel[t] if residual else known_p[t] + offset)
                used.append(known_m[t])
            h_p = (known_p[-1], known_p[-2] if n_known > 1 else h_p[0])
            h_m = (known_m[-1], known_m[-2] if n_known > 1 else h_m[0])
        if free_steps:
            if roll_mask is None:
                raise ValueError("free steps need roll_mask")
            roll = roll_mask.bool()
            rows_idx = torch.nonzero(roll.reshape(-1)).flatten()
            rows = None if len(rows_idx) == r else rows_idx
            # everyone rolled out and present at the two steps before: the masks are all True, and the features
            # are computed without them (the same values); this holds from the third free step on when rows is None
            full = [rows is None and bool(x.all()) for x in h_m]
            if feed is not None and preds:
                preds[-1] = feed(preds[-1], raws[-1])
            prev = preds[-1] if preds else first_pred
            if prev is None:
                raise ValueError("free steps after no known step need first_pred")
            zeros = prev.new_zeros(())
            for k in range(free_steps):
                dense = rows is None and full[0] and full[1]
                p_t = prev if rows is None else torch.where(roll.unsqueeze(-1), prev, zeros)
                node_x, edge_x, vel = self._gate_inputs(w, (p_t, *h_p), None if dense else (roll, *h_m), rows)
                offset = self._advance(w, live, rows, node_x, edge_x).view(b, n, -1)
                if gaussian:
                    raws.append(offset[..., 2:] + self._step_bias(k + 1))
                    offset = offset[..., :2]
                prev = p_t + offset + vel if residual else p_t + offset
                if feed is not None:
                    prev = feed(prev, raws[-1])
                preds.append(prev)
                used.append(roll)
                h_p, h_m = (p_t, h_p[0]), (roll, h_m[0])
                full = [rows is None, full[0]]
        live.flush()
        if not preds:
            none_raw = known_p.new_zeros(0, b, n, 3) if gaussian else None
            return known_p.new_zeros(0, b, n, 2), none_raw, known_m.new_zeros(0, b, n), live.full
        return torch.stack(preds), torch.stack(raws) if gaussian else None, torch.stack(used), live.full

    def step(
        self,
        p: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        m: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        state: dict[str, torch.Tensor],
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One graph step.

        Args:
            p: positions at ``t, t−1, t−2``, each ``(B, N, 2)`` normalised.
            m: presence at ``t, t−1, t−2``, each ``(B, N)`` bool.
            state: hidden states for ``B*N`` rows (see :meth:`init_state`).

        Returns:
            ``(B, N, 2)`` predicted positions at ``t+1`` and the new state (rows absent at ``t`` keep theirs).
        """
        pred, _, new = self.scan(p[0][None], m[0][None].bool(), (p[1], p[2]), (m[1], m[2]), state)
        return pred[0], new

    def forward(
        self, positions: torch.Tensor, mask: torch.Tensor, obs_len: int, teacher_forcing: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run over a whole window batch.

        Args:
            positions: ``(B, T, N, 2)`` normalised positions (only observed steps are read when
                ``teacher_forcing`` is False).
            mask: ``(B, T, N)`` bool presence.
            obs_len: number of observed steps.
            teacher_forcing: feed true positions (and true presence) at every step; otherwise from
                step ``obs_len`` on, feed the model's own predictions for the pedestrians present at
                the last observed step (the true autoregressive rollout used in evaluation).

        Returns:
            ``pred: (B, T−1, N, 2)`` where ``pred[:, t]`` is the prediction of step ``t+1`` (the mean, with the
            gaussian head), and the input mask ``(B, T−1, N)`` used at each step.
        """
        pred, _, used = self.forward_distribution(positions, mask, obs_len, teacher_forcing)
        return pred, used

    def forward_distribution(
        self, positions: torch.Tensor, mask: torch.Tensor, obs_len: int, teacher_forcing: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """:meth:`forward` plus the gaussian head's raw ``(σx, σy, ρ)`` at each step ``(B, T−1, N, 3)`` (None
        with the point head). Without teacher forcing the rollout feeds back the means, so the Gaussian at a
        predicted step is the model's distribution of that step's position given the observed steps."""
        steps = positions.shape[1] - 1
        known = steps if teacher_forcing else min(obs_len, steps)
        return self._run(positions[:, :known], mask[:, :known], steps - known, mask[:, obs_len - 1])

    def _run(
        self,
        positions: torch.Tensor,
        mask: torch.Tensor,
        free_steps: int,
        roll_mask: torch.Tensor,
        feed: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """From a zero state: ``(B, L, N, 2)`` known inputs then ``free_steps``; ``(B, L + free, N, ·)`` out
        (predictions, the head's raw output or None, the masks used)."""
        b, _, n, _ = positions.shape
        m = mask.bool().transpose(0, 1)
        p = torch.where(m.unsqueeze(-1), positions.transpose(0, 1), positions.new_zeros(()))
        zeros_p = positions.new_zeros(b, n, 2)
        zeros_m = torch.zeros(b, n, dtype=torch.bool, device=positions.device)
        state = self.init_state(b * n, positions.device)
        pred, raw, used, _ = self.scan_distribution(
            p, m, (zeros_p, zeros_p), (zeros_m, zeros_m), state, free_steps, roll_mask.bool(), feed=feed
        )
        return pred.transpose(0, 1), None if raw is None else raw.transpose(0, 1), used.transpose(0, 1)

    def rollout(self, obs_positions: torch.Tensor, obs_mask: torch.Tensor, pred_len: int) -> torch.Tensor:
        """Autoregressive forecast from observed steps only.

        Args:
            obs_positions: ``(B, obs_len, N, 2)`` normalised.
            obs_mask: ``(B, obs_len, N)`` bool.
            pred_len: steps to forecast.

        Returns:
            ``(B, pred_len, N, 2)`` normalised; meaningful for pedestrians present at the last observed step
            (the means, with the gaussian head).
        """
        obs_len = obs_positions.shape[1]
        pred, _, _ = self._run(obs_positions, obs_mask, pred_len - 1, obs_mask[:, obs_len - 1])
        return pred[:, obs_len - 1 :]

    def _need_gaussian(self) -> None:
        if not self.gaussian:
            raise ValueError(
                f"this {self.cfg.model!r} network has a point head (head: point); a distribution needs head: gaussian"
            )

    def rollout_distribution(
        self, obs_positions: torch.Tensor, obs_mask: torch.Tensor, pred_len: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The mean rollout (as :meth:`rollout`) and each step's Gaussian; gaussian head only.

        Returns:
            ``mean (B, pred_len, N, 2)``, ``sigma (B, pred_len, N, 2)`` and ``rho (B, pred_len, N)``, normalised units.
        """
        self._need_gaussian()
        obs_len = obs_positions.shape[1]
        pred, raw, _ = self._run(obs_positions, obs_mask, pred_len - 1, obs_mask[:, obs_len - 1])
        assert raw is not None
        sigma, rho = params_from_raw(raw[:, obs_len - 1 :])
        return pred[:, obs_len - 1 :], sigma, rho

    def sample_rollout(
        self,
        obs_positions: torch.Tensor,
        obs_mask: torch.Tensor,
        pred_len: int,
        samples: int,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Sampled futures whose every step is drawn from the step's Gaussian and fed back as the next input
        (the observed steps are run once and their state shared by the samples); gaussian head only.

        Returns:
            ``(B, samples, pred_len, N, 2)`` normalised.
        """
        self._need_gaussian()
        b, obs_len, n, _ = obs_positions.shape
        m = obs_mask.bool()
        p = torch.where(m.unsqueeze(-1), obs_positions, obs_positions.new_zeros(()))
        zeros_p = p.new_zeros(b, n, 2)
        zeros_m = torch.zeros(b, n, dtype=torch.bool, device=p.device)
        state = self.init_state(b * n, p.device)
        pred, raw, _, state = self.scan_distribution(
            p.transpose(0, 1), m.transpose(0, 1), (zeros_p, zeros_p), (zeros_m, zeros_m), state
        )
        assert raw is not None

        def draw(mean: torch.Tensor, raw_t: torch.Tensor) -> torch.Tensor:
            sigma, rho = params_from_raw(raw_t)
            eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
            return gaussian_sample(mean, sigma, rho, eps)

        def rep(x: torch.Tensor, dim: int = 0) -> torch.Tensor:  # (B, ...) -> (B * samples, ...)
            return x.repeat_interleave(samples, dim=dim)

        roll = rep(m[:, -1])
        first = draw(rep(pred[-1]), rep(raw[-1]))
        prev2 = rep(p[:, -2]) if obs_len > 1 else rep(zeros_p)
        prev2_m = rep(m[:, -2]) if obs_len > 1 else rep(zeros_m)
        rows = {k: rep(v.view(*v.shape[:-2], b, n, v.shape[-1]), v.dim() - 2).flatten(-3, -2) for k, v in state.items()}
        rest, _, _, _ = self.scan_distribution(
            first.new_zeros(0, b * samples, n, 2),
            roll.new_zeros(0, b * samples, n),
            (rep(p[:, -1]), prev2),
            (rep(m[:, -1]), prev2_m),
            rows,
            free_steps=pred_len - 1,
            roll_mask=roll,
            first_pred=first,
            feed=draw,
        )
        out = torch.cat([first[None], rest], 0)  # (pred_len, B * samples, N, 2)
        return out.view(pred_len, b, samples, n, 2).permute(1, 2, 0, 3, 4)


__getattr__ = moved_attributes(
    __name__,
    {
        "HEADS": "crowdnav_mesrnn.models.architecture",
        "MODEL_TYPES": "crowdnav_mesrnn.models.architecture",
        "ModelConfig": "crowdnav_mesrnn.models.architecture",
        "lstm_pointwise_from_sigmoid": "crowdnav_mesrnn.models.online",
    },
)
