"""A trained structural RNN behind the :class:`~crowdnav_mesrnn.models.base.Predictor` interface."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.models.architecture import ModelConfig
from crowdnav_mesrnn.models.base import check_history, last_known
from crowdnav_mesrnn.models.gaussian import GaussianForecast, params_from_raw
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
from crowdnav_mesrnn.utils import file_sha256

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

    @property
    def has_distribution(self) -> bool:
        """Whether the network has the gaussian head, so forecasts come with a per-step distribution."""
        return bool(self.net.gaussian)

    def _distribution_needed(self) -> None:
        if not self.has_distribution:
            raise ValueError(
                f"the {self.name!r} predictor{f' of split {self.split!r}' if self.split else ''} has a point head: "
                "it forecasts no distribution (load weights trained with head: gaussian)"
            )

    @torch.no_grad()
    def predict_distribution_batch(
        self, positions_m: torch.Tensor, mask: torch.Tensor, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN
    ) -> GaussianForecast:
        """Batched mean rollout with each step's Gaussian (gaussian head only): ``(B, >=obs_len, N, 2)`` metres
        -> means ``(B, pred_len, N, 2)`` (equal to :meth:`predict_batch`), scales in metres and correlations."""
        self._distribution_needed()
        obs = positions_m[:, :obs_len].float()
        m = mask[:, :obs_len].bool()
        normed = torch.where(m.unsqueeze(-1), self.norm.normalise(obs), torch.zeros_like(obs))
        mean, sigma, rho = self.net.rollout_distribution(normed, m, pred_len)
        scale = torch.as_tensor(self.norm.scale, dtype=sigma.dtype)
        return GaussianForecast(self.norm.denormalise(mean), sigma / scale, rho)

    @torch.no_grad()
    def sample_batch(
        self,
        positions_m: torch.Tensor,
        mask: torch.Tensor,
        samples: int,
        generator: torch.Generator | None = None,
        feedback: bool = False,
        obs_len: int = OBS_LEN,
        pred_len: int = PRED_LEN,
        coherent: bool = False,
    ) -> torch.Tensor:
        """Sampled futures ``(B, samples, pred_len, N, 2)`` metres (gaussian head only).

        Args:
            feedback: False draws every step from its Gaussian of the mean rollout (each step's distribution given
                the observation); True feeds every drawn position back as the next input
                (:meth:`StructuralRNN.sample_rollout`).
            coherent: without feedback, one draw per sample and pedestrian for all steps
                (:meth:`GaussianForecast.draw`) instead of one per step.
        """
        self._distribution_needed()
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        if not feedback:
            dist = self.predict_distribution_batch(positions_m, mask, obs_len, pred_len)
            return dist.draw(samples, generator, coherent=coherent)
        obs = positions_m[:, :obs_len].float()
        m = mask[:, :obs_len].bool()
        normed = torch.where(m.unsqueeze(-1), self.norm.normalise(obs), torch.zeros_like(obs))
        return self.norm.denormalise(self.net.sample_rollout(normed, m, pred_len, samples, generator))

    def forecast_distribution(self, history: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`forecast` with each step's Gaussian (gaussian head only).

        Returns:
            ``mean (N, pred_len, 2)`` metres (equal to :meth:`forecast`), ``sigma (N, pred_len, 2)`` metres and
            ``rho (N, pred_len)``, float32; pedestrians absent at the last observed step have scales and
            correlation 0.
        """
        self._distribution_needed()
        history, mask = check_history(history, mask, self.obs_len)
        n = history.shape[1]
        if n == 0:
            return (
                np.zeros((0, self.pred_len, 2), np.float32),
                np.zeros((0, self.pred_len, 2), np.float32),
                np.zeros((0, self.pred_len), np.float32),
            )
        dist = self.predict_distribution_batch(torch.from_numpy(history)[None], torch.from_numpy(mask)[None])
        mean = dist.mean[0].permute(1, 0, 2).numpy().astype(np.float32)
        sigma = dist.sigma[0].permute(1, 0, 2).numpy().astype(np.float32)
        rho = dist.rho[0].permute(1, 0).numpy().astype(np.float32)
        gone = ~mask[-1]
        mean[gone] = last_known(history, mask)[gone, None, :]
        sigma[gone] = 0.0
        rho[gone] = 0.0
        return mean, sigma, rho

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
    pedestrian); :meth:`forecast` rolls out ``pred_len`` steps from copies of the carried states, so each
    new frame costs one step of the observed encoder plus the rollout. After exactly ``obs_len``
    observations from a fresh start it equals :meth:`LearnedPredictor.forecast` on the same history
    (and :meth:`forecast_distribution` equals :meth:`LearnedPredictor.forecast_distribution`).
    """

    def __init__(self, predictor: LearnedPredictor, num_slots: int) -> None:
        self.p = predictor
        self.n = num_slots
        self.state = predictor.net.init_state(num_slots)
        self.pos = [torch.zeros(1, num_slots, 2) for _ in range(2)]  # t, t-1 (normalised)
        # presence at t, t-1, in numpy (cheaper tests of a few rows) and as tensors sharing its memory
        self.seen = [np.zeros(num_slots, bool) for _ in range(2)]
        self.mask = [torch.from_numpy(s.reshape(1, num_slots)) for s in self.seen]
        self.next_pred = torch.zeros(1, num_slots, 2)
        self.next_raw = torch.zeros(1, num_slots, 3) if predictor.has_distribution else None
        self.last_seen_m = np.zeros((num_slots, 2), np.float32)
        self.steps = 0
        self._scale = torch.as_tensor(predictor.norm.scale, dtype=torch.float32)
        self._lo = torch.as_tensor(predictor.norm.lo, dtype=torch.float32)

    def _gather(self, idx: torch.Tensor | None) -> dict[str, torch.Tensor]:
        if idx is None:
            return dict(self.state)
        return {k: (v[:, idx] if k.startswith("edge") else v[idx]) for k, v in self.state.items()}

    def _scatter(self, idx: torch.Tensor | None, sub: dict[str, torch.Tensor]) -> None:
        if idx is None:
            self.state = dict(sub)
            return
        for k, v in sub.items():
            if k.startswith("edge"):
                self.state[k][:, idx] = v
            else:
                self.state[k][idx] = v

    @torch.inference_mode()
    def observe(self, positions_m: np.ndarray, present: np.ndarray) -> None:
        """One annotation step: ``(num_slots, 2)`` metres and ``(num_slots,)`` bool presence (neither array is kept:
        the caller may refill them in place for the next frame).

        Only pedestrians present now or at the previous step enter the computation (the others
        can neither update nor influence anyone), so the cost follows the crowd, not the slot count.
        """
        pos = np.asarray(positions_m, dtype=np.float32).reshape(self.n, 2)
        # a copy: the presence is kept (as a tensor sharing its memory) for the next steps, and a caller may refill
        # its array in place for the next frame (a tracker's buffer)
        now = np.array(present, dtype=bool).reshape(self.n)
        m = torch.from_numpy(now.reshape(1, self.n))
        normed = (torch.from_numpy(pos)[None] - self._lo) * self._scale - 1.0  # MinMax.normalise, constants cached
        all_now = bool(now.all())
        p_t = normed if all_now else torch.where(m.unsqueeze(-1), normed, torch.zeros(1, self.n, 2))
        net = self.p.net
        live_np = now | self.seen[0]
        every = bool(live_np.all())
        idx = None if every else torch.from_numpy(np.flatnonzero(live_np))

        def cols(x: torch.Tensor) -> torch.Tensor:
            return x if idx is None else x[:, idx]

        if every or len(idx):  # type: ignore[arg-type]
            if not (live_np & ~now).any():  # nobody left since the last frame: all computed rows are present now
                s1, s2 = (s if every else s[live_np] for s in self.seen)
                m1, m2 = cols(self.mask[0])[0], cols(self.mask[1])[0]
                nxt, sub = net.online_step(
                    (cols(p_t)[0], cols(self.pos[0])[0], cols(self.pos[1])[0]),
                    None if s1.all() else m1,
                    None if s2.all() else m2,
                    self._gather(idx),
                )
                raw = net.head_raw(sub["node_h"]) if net.gaussian else None
            else:  # rows that left keep their state: the general step
                nxt_b, raw_b, _, sub = net.scan_distribution(
                    cols(p_t)[None],
                    cols(m)[None],
                    (cols(self.pos[0]), cols(self.pos[1])),
                    (cols(self.mask[0]), cols(self.mask[1])),
                    self._gather(idx),
                )
                nxt, raw = nxt_b[0, 0], None if raw_b is None else raw_b[0, 0]
            self._scatter(idx, sub)
            if idx is None:
                self.next_pred = nxt[None]
                if raw is not None:
                    self.next_raw = raw[None]
            else:
                self.next_pred[:, idx] = nxt
                if raw is not None:
                    assert self.next_raw is not None
                    self.next_raw[:, idx] = raw
        self.pos = [p_t, self.pos[0]]
        self.mask = [m, self.mask[0]]
        self.seen = [now, self.seen[0]]
        self.last_seen_m[now] = pos[now]
        self.steps += 1

    def _rollout(self) -> tuple[np.ndarray, torch.Tensor | None, torch.Tensor | None]:
        """Slots present at the last observation ``(n,)``, their mean rollout ``(pred_len, n, 2)`` normalised and
        the head's raw output ``(pred_len, n, 3)`` (None with the point head); tensors None when nobody is present."""
        net = self.p.net
        every = bool(self.seen[0].all())
        idx = None if every else torch.from_numpy(np.flatnonzero(self.seen[0]))
        if idx is not None and len(idx) == 0:
            return np.zeros(0, dtype=np.int64), None, None

        def cols(x: torch.Tensor) -> torch.Tensor:
            return x if idx is None else x[:, idx]

        first = cols(self.next_pred)[0]
        rest, raws = net.continue_rollout(
            first,
            cols(self.pos[0])[0],
            cols(self.pos[1])[0],
            cols(self.mask[1])[0],
            self._gather(idx),
            self.p.pred_len - 1,
        )
        preds = torch.cat([first[None], rest], 0)  # (pred_len, n, 2)
        raw = None
        if raws is not None:
            assert self.next_raw is not None
            raw = torch.cat([cols(self.next_raw), raws], 0)
        slots = np.arange(self.n) if idx is None else idx.numpy()
        return slots, preds, raw

    @torch.inference_mode()
    def forecast(self) -> np.ndarray:
        """``(num_slots, pred_len, 2)`` metres for pedestrians present at the last observation
        (rolled out together, each step feeding all their predictions back); other slots hold their
        last observed position."""
        slots, preds, _ = self._rollout()
        if preds is None:
            return np.repeat(self.last_seen_m[:, None, :], self.p.pred_len, axis=1)
        metres = ((preds + 1.0) / self._scale + self._lo).permute(1, 0, 2).numpy()  # MinMax.denormalise
        if len(slots) == self.n:
            return np.ascontiguousarray(metres, dtype=np.float32)
        out = np.repeat(self.last_seen_m[:, None, :], self.p.pred_len, axis=1)
        out[slots] = metres
        return out

    @torch.inference_mode()
    def forecast_distribution(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`forecast` with each step's Gaussian (gaussian head only): ``mean (num_slots, pred_len, 2)``
        metres, ``sigma (num_slots, pred_len, 2)`` metres and ``rho (num_slots, pred_len)``, float32; slots not
        present at the last observation hold their last position with scales and correlation 0."""
        self.p._distribution_needed()
        mean = np.repeat(self.last_seen_m[:, None, :], self.p.pred_len, axis=1)
        sigma = np.zeros((self.n, self.p.pred_len, 2), np.float32)
        rho = np.zeros((self.n, self.p.pred_len), np.float32)
        slots, preds, raw = self._rollout()
        if preds is not None:
            assert raw is not None
            s, r = params_from_raw(raw)
            mean[slots] = ((preds + 1.0) / self._scale + self._lo).permute(1, 0, 2).numpy()  # MinMax.denormalise
            sigma[slots] = (s / self._scale).permute(1, 0, 2).numpy()
            rho[slots] = r.permute(1, 0).numpy()
        return mean, sigma, rho


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
    state = ckpt["state_dict"]
    if "base" in ckpt:  # a head fitted on other weights (crowdnav_mesrnn.head_fit): the trunk is theirs
        state = {**_base_state(path, ckpt["base"], cfg), **state}
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not match the config they were saved with: {exc}") from exc
    info = {k: ckpt.get(k) for k in ("train_config", "epoch", "val", "code_version", "selection")}
    return LearnedPredictor(net, MinMax.from_dict(ckpt["norm"]), ck_split, info)


def _base_state(path: Path, base: dict[str, Any], cfg: ModelConfig) -> dict[str, torch.Tensor]:
    """The weights of the point checkpoint that a head-only file at ``path`` was fitted on (``base``: the file name,
    beside ``path``, and its SHA-256); refused when missing, changed since, or of another architecture."""
    src = path.parent / str(base.get("file"))
    if not src.is_file():
        raise CheckpointError(f"{path}: holds only a head fitted on {src.name}, which is missing (expected at {src})")
    digest = file_sha256(src)
    if digest != base.get("sha256"):
        raise CheckpointError(
            f"{path}: its head was fitted on {src.name} with SHA-256 {base.get('sha256')}, but that file now has "
            f"{digest}; refit the head (crowdnav-mesrnn predictor fit-head)"
        )
    ck: dict[str, Any] = torch.load(src, map_location="cpu", weights_only=True)
    theirs = ModelConfig.from_dict(ck["model_config"])
    if replace(theirs, head=cfg.head, scale_detach=cfg.scale_detach) != cfg:
        raise CheckpointError(f"{path}: its config differs from that of {src.name} beyond the head")
    return ck["state_dict"]
