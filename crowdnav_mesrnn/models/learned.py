"""A trained structural RNN behind the :class:`~crowdnav_mesrnn.models.base.Predictor` interface."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.models.base import check_history, last_known
from crowdnav_mesrnn.models.structural_rnn import ModelConfig, StructuralRNN

CHECKPOINT_FORMAT = 1


class CheckpointError(ValueError):
    """A checkpoint is unreadable or does not match the requested model/config."""


class LearnedPredictor:
    """A structural RNN plus the normalisation statistics it was trained with.

    Positions in and out are metres; normalisation is handled inside.
    """

    def __init__(self, net: StructuralRNN, norm: MinMax, split: str | None = None, info: dict | None = None) -> None:
        self.net = net.eval()
        self.norm = norm
        self.split = split
        self.name = net.cfg.model
        self.obs_len = OBS_LEN
        self.pred_len = PRED_LEN
        self.info = info or {}

    @torch.no_grad()
    def predict_batch(
        self, positions_m: torch.Tensor, mask: torch.Tensor, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN
    ) -> torch.Tensor:
        """Batched rollout: ``(B, >=obs_len, N, 2)`` metres (only the first ``obs_len`` steps are read)
        -> ``(B, pred_len, N, 2)`` metres."""
        obs = positions_m[:, :obs_len].float()
        m = mask[:, :obs_len].bool()
        normed = torch.where(m.unsqueeze(-1), self.norm.normalise(obs), torch.zeros_like(obs))
        out = self.net.rollout(normed, m, pred_len)
        return self.norm.denormalise(out)

    def online(self, num_slots: int) -> OnlineForecaster:
        """An incremental forecaster carrying hidden states for ``num_slots`` pedestrians."""
        return OnlineForecaster(self, num_slots)

    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``(obs_len, N, 2)`` metres + ``(obs_len, N)`` mask -> ``(N, pred_len, 2)`` metres."""
        history, mask = check_history(history, mask, self.obs_len)
        n = history.shape[1]
        if n == 0:
            return np.zeros((0, self.pred_len, 2), np.float32)
        pred = self.predict_batch(torch.from_numpy(history)[None], torch.from_numpy(mask)[None])[0]
        out = pred.permute(1, 0, 2).numpy().astype(np.float32)
        gone = ~mask[-1]
        out[gone] = last_known(history, mask)[gone, None, :]
        return out


class OnlineForecaster:
    """Incremental forecasting with hidden states carried per pedestrian between annotation steps.

    Feed one annotation step at a time with :meth:`observe` (slot ``i`` is always the same
    pedestrian); :meth:`forecast` rolls out ``pred_len`` steps from copies of the carried states.
    After exactly ``obs_len`` observations from a fresh start it equals
    :meth:`LearnedPredictor.forecast` on the same history.
    """

    def __init__(self, predictor: LearnedPredictor, num_slots: int) -> None:
        self.p = predictor
        self.n = num_slots
        self.state = predictor.net.init_state(num_slots)
        self.pos = [torch.zeros(1, num_slots, 2) for _ in range(2)]  # t, t-1 (normalised)
        self.mask = [torch.zeros(1, num_slots, dtype=torch.bool) for _ in range(2)]
        self.next_pred = torch.zeros(1, num_slots, 2)
        self.last_seen_m = np.zeros((num_slots, 2), np.float32)
        self.steps = 0

    def _gather(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: (v[:, idx] if k.startswith("edge") else v[idx]) for k, v in self.state.items()}

    def _scatter(self, idx: torch.Tensor, sub: dict[str, torch.Tensor]) -> None:
        for k, v in sub.items():
            if k.startswith("edge"):
                self.state[k][:, idx] = v
            else:
                self.state[k][idx] = v

    @torch.no_grad()
    def observe(self, positions_m: np.ndarray, present: np.ndarray) -> None:
        """One annotation step: ``(num_slots, 2)`` metres and ``(num_slots,)`` bool presence.

        Only pedestrians present now or at the previous step enter the computation (the others
        can neither update nor influence anyone), so the cost follows the crowd, not the slot count.
        """
        pos = np.asarray(positions_m, dtype=np.float32).reshape(self.n, 2)
        m = torch.from_numpy(np.asarray(present, dtype=bool).reshape(1, self.n))
        p_t = torch.where(
            m.unsqueeze(-1), self.p.norm.normalise(torch.from_numpy(pos)[None]), torch.zeros(1, self.n, 2)
        )
        idx = torch.nonzero((m | self.mask[0])[0]).flatten()
        if len(idx):
            nxt, sub = self.p.net.step(
                (p_t[:, idx], self.pos[0][:, idx], self.pos[1][:, idx]),
                (m[:, idx], self.mask[0][:, idx], self.mask[1][:, idx]),
                self._gather(idx),
            )
            self._scatter(idx, sub)
            self.next_pred[:, idx] = nxt
        self.pos = [p_t, self.pos[0]]
        self.mask = [m, self.mask[0]]
        self.last_seen_m[m[0].numpy()] = pos[m[0].numpy()]
        self.steps += 1

    @torch.no_grad()
    def forecast(self) -> np.ndarray:
        """``(num_slots, pred_len, 2)`` metres for pedestrians present at the last observation
        (rolled out together, each step feeding all their predictions back); other slots hold their
        last observed position."""
        net = self.p.net
        out = np.repeat(self.last_seen_m[:, None, :], self.p.pred_len, axis=1)
        idx = torch.nonzero(self.mask[0][0]).flatten()
        if len(idx) == 0:
            return out
        roll = self.mask[0][:, idx]
        first = self.next_pred[:, idx]
        none_p, none_m = first.new_zeros(0, *first.shape), torch.zeros(0, *roll.shape, dtype=torch.bool)
        rest, _, _ = net.scan(
            none_p,
            none_m,
            (self.pos[0][:, idx], self.pos[1][:, idx]),
            (roll, self.mask[1][:, idx]),
            self._gather(idx),
            free_steps=self.p.pred_len - 1,
            roll_mask=roll,
            first_pred=first,
        )
        preds = torch.cat([first, rest[:, 0]], 0)  # (pred_len, n, 2)
        sub = self.p.norm.denormalise(preds).permute(1, 0, 2).numpy().astype(np.float32)
        out[idx.numpy()] = sub
        return out


def lean_state(net: StructuralRNN) -> dict[str, torch.Tensor]:
    """float32 weights only, detached and contiguous."""
    return {k: v.detach().float().contiguous().clone() for k, v in net.state_dict().items()}


def load_predictor(
    path: str | os.PathLike[str], model: str | None = None, split: str | None = None
) -> LearnedPredictor:
    """Load a checkpoint written by training or export.

    Raises:
        CheckpointError: when the file is unreadable, or ``model``/``split`` do not match what it holds,
            or its weights do not fit its config.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no predictor checkpoint at {path}")
    try:
        ckpt: dict[str, Any] = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint ({exc})") from exc
    for key in ("model_config", "state_dict", "norm"):
        if key not in ckpt:
            raise CheckpointError(f"{path}: not a crowdnav-mesrnn predictor checkpoint (missing {key!r})")
    cfg = ModelConfig.from_dict(ckpt["model_config"])
    if model is not None and cfg.model != model:
        raise CheckpointError(f"{path}: holds a {cfg.model!r} model, not {model!r}")
    ck_split = ckpt.get("train_config", {}).get("split")
    if split is not None and ck_split is not None and ck_split != split:
        raise CheckpointError(f"{path}: trained for split {ck_split!r}, not {split!r}")
    if ck_split is not None and ck_split not in SPLITS:
        raise CheckpointError(f"{path}: unknown split {ck_split!r}")
    net = StructuralRNN(cfg)
    try:
        net.load_state_dict(ckpt["state_dict"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not match the config they were saved with: {exc}") from exc
    info = {k: ckpt.get(k) for k in ("train_config", "epoch", "val", "code_version", "selection")}
    return LearnedPredictor(net, MinMax.from_dict(ckpt["norm"]), ck_split, info)
