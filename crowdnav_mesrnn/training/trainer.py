"""Batched, seeded, resumable training of the structural RNN predictors (``crowdnav-mesrnn predictor train``).

:func:`load_configs` merges ``configs/predictor/<model>.yaml`` onto the defaults of :class:`ModelConfig` and
:class:`TrainConfig`; a :class:`Trainer` trains on the split's ``train`` part, selects the epoch on ``val`` (never
``test``) and writes ``last.pt`` / ``best.pt`` checkpoints that resume to the same weights as an uninterrupted run.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.config import ConfigError, check_keys, existing_config, load_yaml, replace_checked
from crowdnav_mesrnn.data.constants import OBS_LEN, check_split
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.recordings import load_split
from crowdnav_mesrnn.data.windows import Window, collate, split_windows
from crowdnav_mesrnn.evaluation.metrics import batches, collect_forecasts, evaluate_windows
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.architecture import ModelConfig
from crowdnav_mesrnn.models.gaussian import params_from_raw
from crowdnav_mesrnn.models.learned import CHECKPOINT_FORMAT, LearnedPredictor, lean_state
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
from crowdnav_mesrnn.utils import atomic_write, code_version

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs" / "predictor"


#: Values of :attr:`TrainConfig.precision`.
PRECISIONS = ("fp32", "bf16")
#: Values of :attr:`TrainConfig.select_on`.
SELECT_ON = ("ade", "nll")


class TrainingDivergedError(RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


@dataclass(frozen=True)
class TrainConfig:
    """How a predictor is trained (paper recipe by default)."""

    split: str = "zara1"
    """Leave-one-out split: trains on its ``train`` part, selects on ``val``, never sees ``test``."""
    epochs: int = 10
    """Passes over the training windows (paper: 10)."""
    batch_size: int = 32
    """Windows per optimiser step (padded together, bucketed by size)."""
    lr: float = 1e-3
    """Adam learning rate (paper: 1e-3)."""
    grad_clip: float = 10.0
    """Gradient norm clip (paper: 10)."""
    teacher_forcing: bool = True
    """Feed true positions over the prediction period (paper). False trains on the model's own rollout."""
    min_scored: int = 2
    """Keep windows with at least this many pedestrians present in all 20 steps."""
    augment_rotation: bool = False
    """Rotate each training window by a random angle about its centre (metres) before normalising."""
    seed: int = 0
    """Seeds shuffling, initialisation, dropout and augmentation."""
    data_dir: str | None = None
    """ETH/UCY folder (default: the usual search order)."""
    max_windows: int = 0
    """Use only the first N training windows (0 = all); for smoke tests."""
    precision: str = "fp32"
    """Arithmetic of the training forward pass: ``fp32``, or ``bf16`` (``torch.autocast`` on the CPU: the
    matmuls in bfloat16 with float32 states, positions and loss; faster on CPUs with AVX-512 BF16, figures in
    ``docs/results/speed.md``). Validation and the shipped weights are always float32."""
    mean_loss: str = "nll"
    """For a distribution head, what trains the means: ``nll`` (the negative log-likelihood, as the scales) or
    ``mse`` (the point head's squared error, :func:`masked_loss`; the likelihood then trains only the scales and
    correlation, its errors taken as constants). With ``mse`` and ``scale_detach`` the point forecast is trained
    exactly as a point head is, and the distribution is fitted to its errors."""
    scale_lr: float | None = None
    """Learning rate of the distribution head's layer (None: ``lr``). The head starts at one scale for every step
    and must reach scales that grow tenfold over the horizon; Adam moves a weight by about the learning rate per
    step, so at the recipe's ``lr`` it takes thousands of steps, while the means (a correction to constant velocity)
    need small moves."""
    nll_beta: float = 0.0
    """β of the β-NLL (Seitzer et al., ICLR 2022) for a distribution head: each position's negative log-likelihood
    is weighted by ``(σx σy)^β`` with the gradient stopped through the weight. 0 is the plain NLL, whose gradient on
    the mean is divided by the variance (a small initial scale then pushes the means hard while the scales are
    still wrong); 1 gives the means the gradient of a squared error. In [0, 1]."""
    select_on: str = "ade"
    """Which validation figure picks ``best.pt`` among the epochs: ``ade`` (metres) or ``nll`` (the negative
    log-likelihood of the true positions under the distribution head's Gaussians; needs ``head: gaussian``)."""
    extra: dict = field(default_factory=dict)
    """Free-form notes recorded with the run (e.g. the config file it came from)."""


def load_configs(
    model: str, config_path: str | os.PathLike[str] | None = None, overrides: dict[str, Any] | None = None
) -> tuple[ModelConfig, TrainConfig]:
    """Merge ``configs/predictor/<model>.yaml`` (or ``config_path``) and overrides onto the defaults.

    The YAML holds two mappings, ``model:`` and ``train:``; unknown keys are errors listing valid keys.
    """
    # a config named but missing is an error (listing those under configs/predictor/), never the defaults
    path = existing_config(config_path, "predictor") if config_path else CONFIG_DIR / f"{model}.yaml"
    raw = load_yaml(path) if path.is_file() else {}
    check_keys(raw, ["model", "train"], f"{path.name}")
    mraw = dict(raw.get("model") or {})
    mraw.setdefault("model", model)
    if mraw["model"] != model:
        raise ConfigError(f"{path}: config is for model {mraw['model']!r}, not {model!r}")
    traw = dict(raw.get("train") or {})
    for key, value in (overrides or {}).items():
        if key in {f for f in ModelConfig.__dataclass_fields__}:
            mraw[key] = value
        else:
            traw[key] = value
    mcfg = ModelConfig.from_dict(mraw)
    tcfg = replace_checked(TrainConfig(), traw, "train config")
    check_split(tcfg.split)
    if tcfg.precision not in PRECISIONS:
        raise ConfigError(f"precision must be one of {', '.join(PRECISIONS)}, got {tcfg.precision!r}")
    if tcfg.scale_lr is not None and not (isinstance(tcfg.scale_lr, float | int) and tcfg.scale_lr > 0):
        raise ConfigError(f"scale_lr must be a positive number or null, got {tcfg.scale_lr!r}")
    if tcfg.mean_loss not in ("nll", "mse"):
        raise ConfigError(f"mean_loss must be 'nll' or 'mse', got {tcfg.mean_loss!r}")
    if not 0.0 <= tcfg.nll_beta <= 1.0:
        raise ConfigError(f"nll_beta must lie in [0, 1], got {tcfg.nll_beta!r}")
    if tcfg.select_on not in SELECT_ON:
        raise ConfigError(f"select_on must be one of {', '.join(SELECT_ON)}, got {tcfg.select_on!r}")
    if tcfg.select_on == "nll" and mcfg.head != "gaussian":
        raise ConfigError("select_on: nll needs a distribution head (model key head: gaussian)")
    return mcfg, tcfg


def keep_freed_memory() -> None:
    """Ask glibc to keep freed memory in the process instead of returning it to the system.

    Training allocates and frees tensors of several MB every step; by default glibc serves them
    with fresh ``mmap`` pages, and the page faults cost a noticeable share of CPU time
    (``docs/results/speed.md``). A no-op where glibc is not the allocator.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name or os.name != "posix":
        return
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    mallopt(m_mmap_threshold, 1 << 30)
    mallopt(m_trim_threshold, 1 << 30)


def rotate_windows(pos: np.ndarray, pres: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rotate each window ``(B, T, N, 2)`` about the mean of its present positions by a random angle."""
    out = pos.copy()
    for b in range(pos.shape[0]):
        pts = pos[b][pres[b]]
        centre = pts.mean(0) if len(pts) else np.zeros(2, np.float32)
        a = rng.uniform(0, 2 * math.pi)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], np.float32)
        out[b] = (pos[b] - centre) @ rot.T + centre
    return np.where(pres[..., None], out, 0.0).astype(np.float32)


def masked_loss(pred: torch.Tensor, used: torch.Tensor, positions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """MSE over the predicted steps (targets ``OBS_LEN..T-1``) where input and target are present."""
    p = pred[:, OBS_LEN - 1 :]
    target = positions[:, OBS_LEN:]
    valid = (used[:, OBS_LEN - 1 :] & mask[:, OBS_LEN:]).unsqueeze(-1).to(p.dtype)
    n = valid.sum().clamp(min=1)
    return (((p - target) ** 2) * valid).sum() / n


def clip_gradients(net: StructuralRNN, max_norm: float) -> None:
    """Clip the gradient norm of the network to ``max_norm``; the distribution head's parameters are clipped on their
    own, so the likelihood's gradients never scale down those of the means (with ``scale_detach`` and
    ``mean_loss: mse`` the means then train exactly as a point head's)."""
    head = net.head_parameters()
    if not head:
        torch.nn.utils.clip_grad_norm_(net.parameters(), max_norm)
        return
    ids = {id(p) for p in head}
    torch.nn.utils.clip_grad_norm_([p for p in net.parameters() if id(p) not in ids], max_norm)
    torch.nn.utils.clip_grad_norm_(head, max_norm)


def make_optimizer(net: StructuralRNN, tcfg: TrainConfig) -> torch.optim.Adam:
    """Adam over every parameter at ``lr``; the distribution head's at ``scale_lr`` when set."""
    if tcfg.scale_lr is None or not net.gaussian:
        return torch.optim.Adam(net.parameters(), lr=tcfg.lr)
    head = net.head_parameters()
    ids = {id(p) for p in head}
    rest = [p for p in net.parameters() if id(p) not in ids]
    return torch.optim.Adam([{"params": rest}, {"params": head, "lr": tcfg.scale_lr}], lr=tcfg.lr)


def gaussian_nll_loss(
    pred: torch.Tensor,
    raw: torch.Tensor,
    used: torch.Tensor,
    positions: torch.Tensor,
    mask: torch.Tensor,
    beta: float = 0.0,
    mean_loss: str = "nll",
) -> torch.Tensor:
    """Mean negative log-likelihood (normalised units) of the targets ``OBS_LEN..T-1`` under the distribution
    head's Gaussians (means ``pred``, raw scales ``raw (B, T−1, N, 3)``), where input and target are present;
    with ``beta > 0`` the β-NLL (each term weighted by the detached ``(σx σy)^β``, :attr:`TrainConfig.nll_beta`);
    with ``mean_loss="mse"`` the means are trained by :func:`masked_loss` and the likelihood sees them as constants
    (:attr:`TrainConfig.mean_loss`)."""
    if mean_loss == "mse":
        return masked_loss(pred, used, positions, mask) + gaussian_nll_loss(
            pred.detach(), raw, used, positions, mask, beta
        )
    p = pred[:, OBS_LEN - 1 :]
    sigma, rho = params_from_raw(raw[:, OBS_LEN - 1 :])
    valid = used[:, OBS_LEN - 1 :] & mask[:, OBS_LEN:]
    target = torch.where(valid.unsqueeze(-1), positions[:, OBS_LEN:], p.detach())
    per = gaussian.nll(target - p, sigma, rho)
    weight = valid.to(per.dtype)
    if beta:
        weight = weight * (sigma[..., 0] * sigma[..., 1]).detach().pow(beta)
    return (per * weight).sum() / valid.sum().clamp(min=1)


def training_loss(
    net: StructuralRNN,
    normed: torch.Tensor,
    mask: torch.Tensor,
    teacher_forcing: bool,
    precision: str = "fp32",
    nll_beta: float = 0.0,
    mean_loss: str = "nll",
) -> torch.Tensor:
    """The loss of one batch ``(B, T, N, 2)`` normalised: :func:`masked_loss` (MSE) for a point head,
    :func:`gaussian_nll_loss` for the distribution head."""
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
        pred, raw, used = net.forward_distribution(normed, mask, OBS_LEN, teacher_forcing=teacher_forcing)
    if raw is None:
        return masked_loss(pred.float(), used, normed, mask)
    return gaussian_nll_loss(pred.float(), raw.float(), used, normed, mask, nll_beta, mean_loss)


class Trainer:
    """Trains one model on one split; checkpoints ``last.pt`` and ``best.pt`` atomically every epoch."""

    def __init__(self, mcfg: ModelConfig, tcfg: TrainConfig, out_dir: str | os.PathLike[str]) -> None:
        self.mcfg, self.tcfg = mcfg, tcfg
        self.out = Path(out_dir)
        torch.manual_seed(tcfg.seed)
        self.net = StructuralRNN(mcfg)
        self.opt = make_optimizer(self.net, tcfg)
        train_recs = load_split(tcfg.split, "train", tcfg.data_dir)
        self.norm = MinMax.fit_recordings(train_recs)
        self.train_windows: list[Window] = split_windows(tcfg.split, "train", tcfg.min_scored, tcfg.data_dir)
        if tcfg.max_windows:
            self.train_windows = self.train_windows[: tcfg.max_windows]
        self.val_windows: list[Window] = split_windows(tcfg.split, "val", 2, tcfg.data_dir)
        if mcfg.standardise:
            self._fit_scales()
        self.epoch = 0
        self.best_val = math.inf
        """The lowest validation figure of ``select_on`` so far."""
        self.best_row: dict[str, float] | None = None
        """The history row of the epoch kept in ``best.pt``."""
        self.history: list[dict[str, float]] = []

    def _fit_scales(self, max_windows: int = 512) -> None:
        rng = np.random.default_rng(self.tcfg.seed)
        pick = rng.permutation(len(self.train_windows))[:max_windows]
        pos, pres, _ = collate([self.train_windows[i] for i in pick])
        p, m = torch.from_numpy(pos), torch.from_numpy(pres)
        self.net.fit_input_scales(torch.where(m.unsqueeze(-1), self.norm.normalise(p), torch.zeros_like(p)), m)

    # ----------------------------------------------------------------- checkpoints
    def _payload(self, full: bool) -> dict[str, Any]:
        payload: dict[str, Any] = {
            "format": CHECKPOINT_FORMAT,
            "model_config": self.mcfg.to_dict(),
            "train_config": asdict(self.tcfg),
            "norm": self.norm.to_dict(),
            "epoch": self.epoch,
            "val": self.history[-1] if self.history else None,
            "history": self.history,
            "best_val": self.best_val,
            **self.best_fields(),
            "code_version": code_version(),
        }
        if full:
            payload["state_dict"] = self.net.state_dict()
            payload["optimizer"] = self.opt.state_dict()
        else:
            payload["state_dict"] = lean_state(self.net)
        return payload

    def save(self, name: str, full: bool = True) -> Path:
        payload = self._payload(full)
        return atomic_write(self.out / name, lambda fh: torch.save(payload, fh))

    def resume(self) -> None:
        """Continue from ``last.pt``; its configs must equal this run's."""
        path = self.out / "last.pt"
        if not path.is_file():
            raise FileNotFoundError(f"cannot resume: no checkpoint at {path}")
        ck = torch.load(path, map_location="cpu", weights_only=True)
        if ck["model_config"] != self.mcfg.to_dict():
            raise ConfigError(
                f"{path}: model config {ck['model_config']} differs from this run's {self.mcfg.to_dict()}"
            )
        defaults = asdict(TrainConfig())
        theirs = {k: v for k, v in {**defaults, **ck["train_config"]}.items() if k != "epochs"}
        ours = {k: v for k, v in asdict(self.tcfg).items() if k != "epochs"}
        if theirs != ours:
            diff = sorted(k for k in ours if ours[k] != theirs.get(k))
            raise ConfigError(f"{path}: train config differs from this run's in {', '.join(diff)}")
        self.net.load_state_dict(ck["state_dict"])
        self.opt.load_state_dict(ck["optimizer"])
        self.epoch = int(ck["epoch"])
        self.history = list(ck["history"])
        self.best_val = float(ck.get("best_val", ck["best_val_ade_m"]))
        key = "val_nll_m" if self.tcfg.select_on == "nll" else "val_ade_m"
        self.best_row = next((h for h in self.history if h.get(key) == self.best_val), None)

    # ----------------------------------------------------------------- training
    def validate(self) -> dict[str, float]:
        """Validation ADE/FDE (and, with the distribution head, ``nll_m``: nats per position, metres)."""
        self.net.eval()
        pred = LearnedPredictor(self.net, self.norm)
        res = evaluate_windows(pred.predict_batch, self.val_windows, self.norm)
        out = {k: res[k] for k in ("ade_m", "fde_m", "ade_norm", "fde_norm")}
        if pred.has_distribution:
            scored = collect_forecasts(self.val_windows, distribution=pred.predict_distribution_batch)
            assert scored.sigma is not None and scored.rho is not None
            out["nll_m"] = float(gaussian.nll(scored.error, scored.sigma, scored.rho).mean())
        return out

    def train_epoch(self, progress: bool = True) -> dict[str, float]:
        t = self.tcfg
        epoch_seed = t.seed * 100_003 + self.epoch
        torch.manual_seed(epoch_seed)
        rng = np.random.default_rng(epoch_seed)
        n_batches = math.ceil(len(self.train_windows) / t.batch_size)
        order = rng.permutation(n_batches)
        self.net.train()
        total, count, seen = 0.0, 0, 0
        t0 = time.perf_counter()
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=len(self.train_windows), desc=f"epoch {self.epoch + 1}/{t.epochs}", unit="win", leave=False
            )
        for chunk in batches(self.train_windows, t.batch_size, order):
            pos, pres, _ = collate([self.train_windows[i] for i in chunk])
            if t.augment_rotation:
                pos = rotate_windows(pos, pres, rng)
            pos_t = torch.from_numpy(pos)
            mask_t = torch.from_numpy(pres)
            normed = torch.where(mask_t.unsqueeze(-1), self.norm.normalise(pos_t), torch.zeros_like(pos_t))
            loss = training_loss(self.net, normed, mask_t, t.teacher_forcing, t.precision, t.nll_beta, t.mean_loss)
            if not torch.isfinite(loss):
                raise TrainingDivergedError(
                    f"loss became {loss.item()} in epoch {self.epoch + 1}; stopped. The last good checkpoint "
                    f"({self.out / 'last.pt'}, epoch {self.epoch}) is kept; try a lower lr or grad_clip."
                )
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            clip_gradients(self.net, t.grad_clip)
            self.opt.step()
            total += loss.item() * len(chunk)
            count += len(chunk)
            seen += len(chunk)
            if bar is not None:
                bar.update(len(chunk))
                bar.set_postfix(loss=f"{total / count:.5f}", wps=f"{seen / (time.perf_counter() - t0):.0f}")
        if bar is not None:
            bar.close()
        return {"train_loss": total / max(count, 1), "windows_per_s": seen / (time.perf_counter() - t0)}

    def fit(self, progress: bool = True, log: Any = print, tensorboard: bool = False) -> dict[str, Any]:
        keep_freed_memory()
        writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(self.out / "tb"))
        while self.epoch < self.tcfg.epochs:
            stats = self.train_epoch(progress)
            val = self.validate()
            self.epoch += 1
            row = {"epoch": self.epoch, **stats, **{f"val_{k}": v for k, v in val.items()}}
            self.history.append(row)
            key = "nll_m" if self.tcfg.select_on == "nll" else "ade_m"
            improved = val[key] < self.best_val
            if improved:
                self.best_val = val[key]
                self.best_row = row
            self.save("last.pt", full=True)
            if improved:
                self.save("best.pt", full=False)
            if writer is not None:
                for k, v in row.items():
                    if k != "epoch":
                        writer.add_scalar(k, v, self.epoch)
            nll = f" NLL {val['nll_m']:.3f}" if "nll_m" in val else ""
            log(
                f"epoch {self.epoch}/{self.tcfg.epochs} loss {stats['train_loss']:.5f} "
                f"val ADE/FDE {val['ade_m']:.3f}/{val['fde_m']:.3f} m{nll} "
                f"({stats['windows_per_s']:.0f} windows/s){' *' if improved else ''}"
            )
        if writer is not None:
            writer.close()
        return {**self.best_fields(), "history": self.history, "out_dir": str(self.out)}

    def best_fields(self) -> dict[str, Any]:
        """What selection reads: ``best_val_ade_m`` (the validation ADE of the epoch kept in ``best.pt``: the
        lowest with ``select_on: ade``), with the distribution head ``best_val_nll_m`` (that epoch's NLL), and
        ``select_on``."""
        row = self.best_row or {}
        out: dict[str, Any] = {"select_on": self.tcfg.select_on}
        if self.tcfg.select_on == "ade":
            out["best_val_ade_m"] = self.best_val
        else:
            out["best_val_ade_m"] = float(row.get("val_ade_m", math.inf))
        if "val_nll_m" in row:
            out["best_val_nll_m"] = float(row["val_nll_m"])
        return out
