"""The recurrence of the structural RNN: LSTM arithmetic with one sigmoid for every gate, the grouped edge cell,
and the bookkeeping of which pedestrians' states are computed at a step.

``tanh(z) = 2 σ(2z) − 1`` is exact in real arithmetic; doubling the cell candidate's weights (:func:`gate_scale`) is
exact in floating point, so one sigmoid serves the four gates.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn


def gate_scale(hidden: int, like: torch.Tensor) -> torch.Tensor:
    """``(4 hidden,)`` column multipliers for LSTM gates ``[i, f, g, o]``: 2 on the cell candidate ``g``.

    With the candidate's pre-activation doubled, one sigmoid serves all four gates:
    ``tanh(z) = 2 σ(2z) − 1``. Scaling weights by 2 is exact in floating point.
    """
    scale = torch.ones(4 * hidden, dtype=like.dtype, device=like.device)
    scale[2 * hidden : 3 * hidden] = 2.0
    return scale


def tanh_from_doubled(z2: torch.Tensor) -> torch.Tensor:
    """``tanh(z)`` given ``z2 = 2 z``, as ``2 σ(2z) − 1``: the same function through the sigmoid kernel,
    which is faster than ``torch.tanh`` on CPUs (figures: ``docs/results/speed.md``)."""
    return torch.sigmoid(z2).mul(2.0).sub_(1.0)


def lstm_pointwise(gates: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The LSTM update from pre-activations ``(..., 4H)`` ordered ``[i, f, g, o]`` whose ``g`` block is
    already doubled (see :func:`gate_scale`); returns ``(h, c)``, each ``(..., H)``."""
    s = torch.sigmoid(gates)
    i, f, g, o = s.chunk(4, dim=-1)
    c_new = torch.addcmul(f * c, i, g.mul(2.0).sub_(1.0))
    return o * tanh_from_doubled(c_new * 2.0), c_new


class GroupedLSTMCell(nn.Module):
    """``K`` independent LSTM cells (one per meta-path type) evaluated with batched matmuls.

    Input ``x: (K, R, in)``, state ``(h, c): (K, R, hidden)``. :class:`StructuralRNN` reads the weights
    directly (one batched matmul for all types per step); :meth:`forward` is the plain definition.
    """

    def __init__(self, groups: int, input_size: int, hidden_size: int) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        k = 1.0 / math.sqrt(hidden_size)
        self.weight = nn.Parameter(torch.empty(groups, input_size + hidden_size, 4 * hidden_size).uniform_(-k, k))
        self.bias = nn.Parameter(torch.empty(groups, 1, 4 * hidden_size).uniform_(-k, k))

    def forward(self, x: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        gates = torch.baddbmm(self.bias, torch.cat([x, h], dim=-1), self.weight)
        i, f, g, o = gates.chunk(4, dim=-1)
        c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h_new = torch.sigmoid(o) * torch.tanh(c_new)
        return h_new, c_new


class LiveRows:
    """Hidden states split into the rows computed at the current step and the frozen rest.

    Rows absent at a step keep their state, so only present rows are computed: their states are
    gathered from the full state when the set of present rows changes (and scattered back first);
    while the set stays the same (e.g. the whole rollout) they stay gathered. When every row is
    present no index operation is done at all.
    """

    def __init__(self, state: dict[str, torch.Tensor], decode: Any) -> None:
        self.full = dict(state)
        self.decode = decode
        self.rows: torch.Tensor | None = None
        self.all = False
        self.sub: dict[str, torch.Tensor] = {}
        self.frozen_offsets: torch.Tensor | None = None

    @staticmethod
    def _dim(key: str) -> int:
        return 1 if key.startswith("edge") else 0

    def select(self, rows: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """States of ``rows`` (``None``: every row)."""
        if self.sub:
            if rows is None and self.all:
                return self.sub
            if rows is not None and self.rows is not None and rows.shape == self.rows.shape:
                if torch.equal(rows, self.rows):
                    return self.sub
        self.flush()
        self.all = rows is None
        self.rows = rows
        if rows is None:
            self.sub = dict(self.full)
        else:
            self.sub = {k: v.index_select(self._dim(k), rows) for k, v in self.full.items()}
        return self.sub

    def flush(self) -> None:
        """Write the live rows back into the full state."""
        if not self.sub:
            return
        if self.all:
            self.full = dict(self.sub)
        else:
            assert self.rows is not None
            for k, v in self.sub.items():
                self.full[k] = self.full[k].index_copy(self._dim(k), self.rows, v)
        self.sub, self.rows, self.all, self.frozen_offsets = {}, None, False, None

    def offsets(self, live: torch.Tensor) -> torch.Tensor:
        """``(R, 2)`` decoder offsets of every row from the live rows' ``live (P, 2)``; frozen rows
        are decoded from their kept state (once per set of live rows)."""
        if self.all:
            return live
        if self.frozen_offsets is None:
            self.frozen_offsets = self.decode(self.full["node_h"])
        assert self.rows is not None
        return self.frozen_offsets.index_copy(0, self.rows, live)
