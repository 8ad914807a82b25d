"""One structural RNN, three models: MESRNN {S,T,SS,ST,TS,TT}, SRNN {S,T}, VLSTM {}.

Per meta-path type an EdgeRNN (linear embedding + tanh + dropout, LSTM cell) reads the summed
feature of that type; the NodeRNN reads an embedding of the node's own position concatenated with
the edge hidden states and decodes an offset (linear + tanh); next position = current + offset.
All pedestrians of all windows step together; an absent pedestrian neither updates its hidden
states nor influences its neighbours (its features and its contribution to theirs are masked).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
from torch import nn

from crowdnav_mesrnn.config import ConfigError, replace_checked
from crowdnav_mesrnn.graph.metapaths import metapath_features_step

MODEL_TYPES: dict[str, tuple[str, ...]] = {
    "mesrnn": ("S", "T", "SS", "ST", "TS", "TT"),
    "srnn": ("S", "T"),
    "vlstm": (),
}


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of a structural RNN (paper sizes by default)."""

    model: str = "mesrnn"
    """Which model: ``mesrnn``, ``srnn`` or ``vlstm``; fixes the meta-path types."""
    node_embed: int = 128
    """Node embedding size (paper: 128)."""
    node_hidden: int = 256
    """NodeRNN LSTM hidden size (paper: 256)."""
    edge_embed: int = 64
    """EdgeRNN embedding size (paper: 64)."""
    edge_hidden: int = 128
    """EdgeRNN LSTM hidden size (paper: 128)."""
    dropout: float = 0.0
    """Dropout after the embeddings (training only)."""
    aggregate: str = "sum"
    """How meta-paths are pooled over neighbours: ``sum`` (paper) or ``mean``."""
    feature_scale: float = 1.0
    """Multiplier on edge features before the embedding (1 = paper)."""
    node_input: str = "position"
    """What the node embedding reads: ``position`` (paper) or ``velocity`` (last displacement; scene-independent)."""
    offset: str = "absolute"
    """What the decoder's offset is added to: ``absolute`` (paper: current position) or ``cv_residual``
    (current position plus the last displacement, so the network learns a correction to constant velocity;
    the decoder starts at zero, i.e. the untrained model is exactly constant velocity)."""
    standardise: bool = False
    """Scale every edge feature type and the node input by the inverse of its RMS on the training data
    (fitted once before training, stored with the weights). Off in the paper."""
    types: tuple[str, ...] = field(default=())
    """Meta-path types; filled from ``model`` (not set by hand)."""

    def __post_init__(self) -> None:
        if self.model not in MODEL_TYPES:
            raise ConfigError(f"unknown model {self.model!r}; valid models: {', '.join(MODEL_TYPES)}")
        if self.aggregate not in ("sum", "mean"):
            raise ConfigError(f"aggregate must be 'sum' or 'mean', got {self.aggregate!r}")
        if self.node_input not in ("position", "velocity"):
            raise ConfigError(f"node_input must be 'position' or 'velocity', got {self.node_input!r}")
        if self.offset not in ("absolute", "cv_residual"):
            raise ConfigError(f"offset must be 'absolute' or 'cv_residual', got {self.offset!r}")
        if self.types != MODEL_TYPES[self.model]:
            if self.types:
                raise ConfigError(f"types {self.types} do not match model {self.model!r} ({MODEL_TYPES[self.model]})")
            object.__setattr__(self, "types", MODEL_TYPES[self.model])
        for name in ("node_embed", "node_hidden", "edge_embed", "edge_hidden"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        d = dict(d)
        if "types" in d:
            d["types"] = tuple(d["types"])
        return replace_checked(cls(model=d.get("model", "mesrnn")), d, "model config")

    def to_dict(self) -> dict:
        out = asdict(self)
        out["types"] = list(self.types)
        return out


class GroupedLSTMCell(nn.Module):
    """``K`` independent LSTM cells (one per meta-path type) evaluated with batched matmuls.

    Input ``x: (K, R, in)``, state ``(h, c): (K, R, hidden)``.
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


class StructuralRNN(nn.Module):
    """The structural RNN over a spatio-temporal graph; positions in normalised units."""

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

    def _features(self, p: tuple[torch.Tensor, ...], m: tuple[torch.Tensor, ...]) -> torch.Tensor | None:
        """``(K, B*N, 2)`` edge features at one step from positions/masks at t, t−1, t−2 (each ``(B, N, ·)``)."""
        if not self.types:
            return None
        feats = metapath_features_step(p[0], p[1], p[2], m[0], m[1], m[2], self.types)
        if self.cfg.aggregate == "mean":
            n_t = m[0].sum(-1, keepdim=True).unsqueeze(-1).to(p[0].dtype)  # (B, 1, 1)
            n_prev = m[1].sum(-1, keepdim=True).unsqueeze(-1).to(p[0].dtype)
            nb = (n_t - 1).clamp(min=1)
            scale = {"S": nb, "ST": nb, "SS": nb * (n_t - 2).clamp(min=1), "TS": (n_prev - 1).clamp(min=1)}
            feats = {k: v / scale[k] if k in scale else v for k, v in feats.items()}
        stacked = torch.stack([feats[t] for t in self.types], dim=0)  # (K, B, N, 2)
        if self.cfg.feature_scale != 1.0:
            stacked = stacked * self.cfg.feature_scale
        return stacked.flatten(1, 2) * self.edge_scale[: len(self.types)]

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
        flat = lambda x: x.flatten(0, 1)  # noqa: E731 - (B*T, N, ...)
        pres = flat(m)
        if self.types:
            feats = self._features((flat(positions), flat(p1), flat(p2)), (pres, flat(m1), flat(m2)))
            assert feats is not None
            sel = feats[:, pres.reshape(-1)]  # (K, present rows, 2)
            rms = sel.pow(2).mean(1, keepdim=True).sqrt().clamp(min=1e-6)
            self.edge_scale[: len(self.types)] = 1.0 / rms
        if self.cfg.node_input == "velocity":
            both = m & m1
            vel = (positions - p1)[both]
        else:
            vel = positions[m]
        self.node_scale.copy_(1.0 / vel.pow(2).mean(0).sqrt().clamp(min=1e-6))

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
        b, n, _ = p[0].shape
        present = m[0].reshape(b * n, 1)
        vel = (p[0] - p[1]) * (m[0] & m[1]).unsqueeze(-1).to(p[0].dtype)
        if self.cfg.node_input == "velocity":
            node_in = vel
        else:
            node_in = p[0]
        x_node = self.drop(torch.tanh(self.node_embed(node_in.reshape(b * n, 2) * self.node_scale)))
        edge = self._features(p, m)
        new = dict(state)
        if edge is not None:
            e = self.drop(torch.tanh(torch.baddbmm(self.edge_embed_b, edge, self.edge_embed_w)))
            eh, ec = self.edge_cell(e, state["edge_h"], state["edge_c"])
            new["edge_h"] = torch.where(present.unsqueeze(0), eh, state["edge_h"])
            new["edge_c"] = torch.where(present.unsqueeze(0), ec, state["edge_c"])
            x_node = torch.cat([x_node, new["edge_h"].permute(1, 0, 2).reshape(b * n, -1)], dim=-1)
        nh, nc = self.node_cell(x_node, (state["node_h"], state["node_c"]))
        new["node_h"] = torch.where(present, nh, state["node_h"])
        new["node_c"] = torch.where(present, nc, state["node_c"])
        offset = torch.tanh(self.decoder(new["node_h"])).reshape(b, n, 2)
        if self.cfg.offset == "cv_residual":
            offset = offset + vel
        return p[0] + offset, new

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
            ``pred: (B, T−1, N, 2)`` where ``pred[:, t]`` is the prediction of step ``t+1``, and the
            input mask ``(B, T−1, N)`` used at each step.
        """
        b, t_len, n, _ = positions.shape
        state = self.init_state(b * n, positions.device)
        zeros_p = positions.new_zeros(b, n, 2)
        zeros_m = torch.zeros(b, n, dtype=torch.bool, device=positions.device)
        hist_p = [zeros_p, zeros_p]
        hist_m = [zeros_m, zeros_m]
        roll_mask = mask[:, obs_len - 1]
        preds, used = [], []
        pred = zeros_p
        for t in range(t_len - 1):
            if t < obs_len or teacher_forcing:
                p_t, m_t = positions[:, t], mask[:, t]
            else:
                p_t, m_t = pred, roll_mask
            p_t = torch.where(m_t.unsqueeze(-1), p_t, zeros_p)
            pred, state = self.step((p_t, hist_p[0], hist_p[1]), (m_t, hist_m[0], hist_m[1]), state)
            preds.append(pred)
            used.append(m_t)
            hist_p = [p_t, hist_p[0]]
            hist_m = [m_t, hist_m[0]]
        return torch.stack(preds, dim=1), torch.stack(used, dim=1)

    def rollout(self, obs_positions: torch.Tensor, obs_mask: torch.Tensor, pred_len: int) -> torch.Tensor:
        """Autoregressive forecast from observed steps only.

        Args:
            obs_positions: ``(B, obs_len, N, 2)`` normalised.
            obs_mask: ``(B, obs_len, N)`` bool.
            pred_len: steps to forecast.

        Returns:
            ``(B, pred_len, N, 2)`` normalised; meaningful for pedestrians present at the last observed step.
        """
        b, obs_len, n, _ = obs_positions.shape
        pad_p = obs_positions.new_zeros(b, pred_len, n, 2)
        pad_m = torch.zeros(b, pred_len, n, dtype=torch.bool, device=obs_mask.device)
        pred, _ = self.forward(
            torch.cat([obs_positions, pad_p], 1), torch.cat([obs_mask.bool(), pad_m], 1), obs_len, teacher_forcing=False
        )
        return pred[:, obs_len - 1 :]
