"""The online path of the structural RNN: one step at a time for the few dozen pedestrians a robot tracks.

:class:`OnlineInference` is mixed into :class:`~crowdnav_mesrnn.models.structural_rnn.StructuralRNN`; its methods
are inference only and give the forecasts of :meth:`StructuralRNN.step` and :meth:`StructuralRNN.scan_distribution`
up to float32 rounding (``tests/models/test_gaussian_head.py``), with the operations regrouped for one forecast:
the masks skipped when everyone is present, the meta-paths summed in ``O(N)``, each LSTM's input and recurrent
products in one matrix product, and the node LSTM's weights prepacked where the torch build has oneDNN.
"""

from __future__ import annotations

from typing import Any

import torch

from crowdnav_mesrnn.graph.metapaths import dense_features_centred


def lstm_pointwise_from_sigmoid(s: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`~crowdnav_mesrnn.models.recurrence.lstm_pointwise` given the gates' sigmoid ``s`` (a matrix product with the sigmoid fused), in fewer
    operations (``i (2g − 1) = 2 i g − i``, ``o (2 s − 1) = 2 o s − o``): the same function, different float32
    rounding; used by the online path only."""
    i, f, g, o = s.chunk(4, dim=-1)
    c_new = torch.addcmul(-i, f, c).addcmul_(i, g, value=2.0)
    return torch.addcmul(-o, o, c_new.mul(2.0).sigmoid_(), value=2.0), c_new


class OnlineInference:
    """The online methods of :class:`~crowdnav_mesrnn.models.structural_rnn.StructuralRNN` (a mixin: they read the
    network's config, weights and caches, and hold none of their own)."""

    def online_weights(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """``(self._weights(), self._online_weights())`` with one check of the parameters' versions (inference)."""
        key = tuple(v for p in [*self.parameters(), *self.buffers()] for v in (p.data_ptr(), p._version))
        if self._online is not None and self._online[0] == key and self._prepared is not None:
            return self._prepared[1], self._online[1]
        return self._weights(), self._online_weights()

    def _online_weights(self) -> dict[str, Any]:
        """Weights of :meth:`continue_rollout` (inference only): the input and recurrent halves of every LSTM in one
        matrix each (one product per LSTM and step), and the node LSTM's matrix prepacked for oneDNN where this
        torch build has it. Cached like :meth:`_weights`."""
        w = self._weights()
        key = tuple(v for p in [*self.parameters(), *self.buffers()] for v in (p.data_ptr(), p._version))
        if self._online is not None and self._online[0] == key:
            return self._online[1]
        # The embeddings enter as σ(2z) = (tanh z + 1) / 2 (one operation less each): the affine map is folded into
        # the weights and biases of the products they feed, ``tanh(z) W + b = σ(2z) (2 W) + (b − Σ_rows W)``.
        node_w = torch.cat([w["node_x_w"] * 2.0, w["node_rec_w"]], 0)  # (embed + K edge_hidden + node_hidden, 4 H)
        node_b = w["node_b"] - w["node_x_w"].sum(0)
        out: dict[str, Any] = {"node_w": node_w.contiguous(), "node_b": node_b.contiguous(), "packed": None}
        out["node_embed_w"] = (self.node_scale[:, None] * w["node_embed_w"]).detach().contiguous()  # input scale folded
        try:  # the product of the node LSTM, the largest of a step, prepacked (oneDNN, x86 builds)
            packed = torch.ops.mkldnn._reorder_linear_weight(node_w.t().contiguous(), 64)
            out["packed"] = (packed, torch.ops.mkldnn._linear_pointwise)
        except (AttributeError, RuntimeError):
            pass
        if self.types:
            out["edge_w"] = torch.cat([w["edge_x_w"] * 2.0, w["edge_h_w"]], 1).contiguous()  # (K, embed + hidden, 4 H)
            out["edge_b"] = (w["edge_b"] - w["edge_x_w"].sum(1, keepdim=True)).contiguous()  # (K, 1, 4 H)
        out["decoder_w"] = self.decoder.weight.detach().t().contiguous()
        out["decoder_b"] = self.decoder.bias.detach().contiguous()
        if self.gaussian:
            out["head_w"] = self.scale_head.weight.detach().t().contiguous()
            out["head_b"] = self.scale_head.bias.detach().contiguous()
        self._online = (key, out)
        return out

    def online_step(
        self,
        p: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        m_tm1: torch.Tensor | None,
        m_tm2: torch.Tensor | None,
        state: dict[str, torch.Tensor],
        weights: tuple[dict[str, torch.Tensor], dict[str, Any]] | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One step of :meth:`step` for online forecasting (inference only) when all ``n`` pedestrians are present
        at ``t``, with the operations regrouped for one forecast of a few dozen pedestrians (equal to float32
        rounding, ``tests/models/test_gaussian_head.py``): when everyone is also present at ``t − 1`` and ``t − 2``
        the masks are skipped and the meta-paths are summed in ``O(N)`` (:func:`dense_features_centred`), each LSTM's
        input and recurrent products are one matrix product, and the node LSTM's weights are prepacked. The distribution head is not applied (see :meth:`continue_rollout`).

        Args:
            p: positions at ``t, t − 1, t − 2``, each ``(n, 2)`` normalised (0 where absent).
            m_tm1, m_tm2: ``(n,)`` bool presence at ``t − 1`` and ``t − 2`` (None: everyone present).
            state: hidden states of the ``n`` rows (not modified).
            weights: ``(self._weights(), self._online_weights())`` when the caller already has them (looking them
                up checks every parameter's version, at every step).

        Returns:
            ``(n, 2)`` the (mean) prediction of step ``t + 1`` and the new state.
        """
        w, ow = weights if weights is not None else self.online_weights()
        n, k = p[0].shape[0], len(self.types)
        masks = None
        if m_tm1 is not None or m_tm2 is not None:
            ones = torch.ones(1, n, dtype=torch.bool)
            masks = (ones, ones if m_tm1 is None else m_tm1[None], ones if m_tm2 is None else m_tm2[None])
        if masks is None and k:  # the input scales are folded into the embedding's weights
            feats, vel, factors = dense_features_centred(p[0], p[1], p[2], self.types)
            edge_embed_w = self._online_edge_embed_w(n, factors, w, ow)
        else:
            feats, vel = self._features((p[0][None], p[1][None], p[2][None]), masks)
            vel = vel[0]
            edge_embed_w = w.get("edge_embed_w")
        node_in = vel if self.cfg.node_input == "velocity" else p[0]
        # the embeddings as σ(2z), not tanh(z) = 2 σ(2z) − 1: the online weights take the difference (_online_weights)
        x = torch.addmm(w["node_embed_b"], node_in, ow["node_embed_w"]).sigmoid_()
        new: dict[str, torch.Tensor] = {}
        if k:
            assert feats is not None
            e = torch.baddbmm(w["edge_embed_b"], feats.reshape(k, -1, 2), edge_embed_w).sigmoid_()
            gates = torch.baddbmm(ow["edge_b"], torch.cat([e, state["edge_h"]], -1), ow["edge_w"])
            new["edge_h"], new["edge_c"] = lstm_pointwise_from_sigmoid(gates.sigmoid_(), state["edge_c"])
            z = torch.cat([x, *new["edge_h"].unbind(0), state["node_h"]], 1)
        else:
            new["edge_h"], new["edge_c"] = state["edge_h"], state["edge_c"]
            z = torch.cat([x, state["node_h"]], 1)
        packed = ow["packed"] if n >= 8 else None  # prepacking pays only for enough rows
        if packed is not None:  # the gates' sigmoid fused into the product
            gate_s = packed[1](z, packed[0], ow["node_b"], "sigmoid", [], "")
        else:
            gate_s = torch.addmm(ow["node_b"], z, ow["node_w"]).sigmoid_()
        new["node_h"], new["node_c"] = lstm_pointwise_from_sigmoid(gate_s, state["node_c"])
        offset = torch.addmm(ow["decoder_b"], new["node_h"], ow["decoder_w"]).tanh_()
        nxt = torch.add(p[0], vel).add_(offset) if self.cfg.offset == "cv_residual" else offset.add_(p[0])
        return nxt, new

    def _online_edge_embed_w(
        self, n: int, factors: tuple[float, ...], w: dict[str, torch.Tensor], ow: dict[str, Any]
    ) -> torch.Tensor:
        """``(K, 2, edge_embed)``: the edge embedding's (doubled) weights with the features' left-out ``factors``
        (:func:`dense_features_centred`), the mean aggregation's divisors (everyone of ``n`` present),
        ``feature_scale`` and the input scales folded in, cached per ``n`` in the online weights ``ow`` (no product
        of the features per step)."""
        cache = ow.setdefault("edge_embed_w", {})
        if n not in cache:
            k = len(self.types)
            nb = float(max(n - 1, 1))
            div = {"S": nb, "ST": nb, "SS": nb * max(n - 2, 1), "TS": nb} if self.cfg.aggregate == "mean" else {}
            inv = torch.tensor(
                [f / div.get(t, 1.0) for t, f in zip(self.types, factors, strict=True)], dtype=self.edge_scale.dtype
            )
            scale = inv[:, None, None] * self.cfg.feature_scale * self.edge_scale[:k]  # (K, 1, 2)
            cache[n] = (scale.transpose(1, 2) * w["edge_embed_w"]).contiguous()
        return cache[n]

    def continue_rollout(
        self,
        first: torch.Tensor,
        p_t: torch.Tensor,
        p_tm1: torch.Tensor,
        m_tm1: torch.Tensor,
        state: dict[str, torch.Tensor],
        steps: int,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The free steps of :meth:`scan_distribution` after an observed step ``t``, by :meth:`online_step`
        (inference only), for ``n`` pedestrians all present at ``t`` and all rolled out.

        Args:
            first: ``(n, 2)`` the prediction of step ``t + 1`` (the observed step's output), normalised.
            p_t, p_tm1: ``(n, 2)`` positions at ``t`` and ``t − 1`` (0 where absent), normalised.
            m_tm1: ``(n,)`` bool presence at ``t − 1``.
            state: hidden states of the ``n`` rows after step ``t`` (not modified).
            steps: free steps after ``first``.

        Returns:
            ``(steps, n, 2)`` the means of steps ``t + 2 ..`` and, with the gaussian head, the raw ``(σx, σy, ρ)``
            ``(steps, n, 3)`` (None with the point head), computed for all steps at once after the loop.
        """
        n = first.shape[0]
        cur, h0, h1 = first, p_t, p_tm1
        m2: torch.Tensor | None = None if bool(m_tm1.all()) else m_tm1  # presence at t − 1, for the first step
        preds: list[torch.Tensor] = []
        hs: list[torch.Tensor] = []
        weights = self.online_weights()
        for _ in range(steps):
            nxt, state = self.online_step((cur, h0, h1), None, m2, state, weights)
            h1, h0, cur, m2 = h0, cur, nxt, None
            preds.append(nxt)
            hs.append(state["node_h"])
        if not preds:
            return first.new_zeros(0, n, 2), (first.new_zeros(0, n, 3) if self.gaussian else None)
        raw = None
        if self.gaussian:
            ahead = torch.arange(1, steps + 1).clamp(max=len(self.step_bias) - 1)
            ow = weights[1]
            raw = torch.addmm(ow["head_b"], torch.cat(hs, 0), ow["head_w"]).view(steps, n, 3)
            raw = raw + self.step_bias.detach()[ahead][:, None]
        return torch.stack(preds), raw
