"""Fit the distribution head on shipped point weights, the trunk frozen: ``crowdnav-mesrnn predictor fit-head``.

**This is not the declared plan of** ``configs/predictor/gaussian.yaml`` (VLSTM, SRNN and MESRNN × 5 splits ×
2 candidates, then 3 seeds of each winner) **but its head-only shortcut.** It loads the shipped
point weights ``crowdnav_mesrnn/pretrained/<model>_<split>.pt``, keeps every one of their parameters as it is, and
fits only the Gaussian head (``scale_head`` and ``step_bias`` of :class:`StructuralRNN`: ``3 (node_hidden + 1) +
3 · PRED_LEN`` numbers) by negative log-likelihood on the split's training windows, stopping on the validation NLL.
It writes ``<model>_gaussian_<split>.pt`` beside the point weights, where ``predictor evaluate/calibrate --head
gaussian`` look (:func:`crowdnav_mesrnn.models.pretrained.pretrained_path`).

Why it is equivalent for the trunk: the declared recipe (``scale_detach: true``, ``mean_loss: mse``, the head's
gradients clipped on their own) trains every trunk and decoder parameter exactly as the point recipe does: the same
weights for the same seed at every epoch (``tests/training/test_training_gaussian.py``). The trunk of any run of the plan is
therefore the trunk of the point run with the same candidate, seed and epoch, and the point forecast is unchanged.

Where the shortcut differs from the plan (both select on validation data only, never on the test scene):

- **Which trunk.** The plan keeps, per run, the epoch of lowest validation NLL, and per model and split the candidate
  and seed of lowest validation NLL. The shortcut keeps the trunk that validation ADE selected (the shipped point
  weights: their candidate, seed and epoch) and selects only the head's epoch, on validation NLL.
- **What the head sees.** The plan's head learns alongside a trunk that is still training (on rotated windows for
  the rotation candidate). Here the head is fitted to the final trunk's node states, on the unrotated training windows.

The file holds only the head's tensors plus the name and SHA-256 of the point weights it was fitted on
(:func:`crowdnav_mesrnn.models.learned.load_predictor` joins the two and refuses point weights whose hash differs).
So it stays a few kilobytes, and its trunk is the shipped point weights to the bit.

The fit is cheap because the head reads the node state without feeding anything back: the rollout feeds back the
means, so the node states along it are those of the point forecast. They are computed once per window
(:func:`head_rows`), and the head's epochs run on the cached ``(rows, node_hidden)`` matrix.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.windows import Window, collate, split_windows
from crowdnav_mesrnn.evaluation.metrics import batches, collect_forecasts
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.gaussian import params_from_raw
from crowdnav_mesrnn.models.learned import CHECKPOINT_FORMAT, CheckpointError, LearnedPredictor, load_predictor
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
from crowdnav_mesrnn.utils import atomic_write, code_version, file_sha256

#: Why the file exists, recorded in it (``selection.note``) and printed by ``predictor evaluate``.
SHORTCUT_NOTE = (
    "head-only shortcut of configs/predictor/gaussian.yaml (not the declared plan): the Gaussian head fitted by NLL "
    "on the split's training windows, on the shipped point weights with every trunk and decoder parameter frozen "
    "(the declared recipe trains the trunk exactly as the point recipe), head epoch selected on validation NLL"
)
#: Parameter names of the distribution head (everything else is the trunk, frozen).
HEAD_KEYS: tuple[str, ...] = ("scale_head.weight", "scale_head.bias", "step_bias")


@dataclass(frozen=True)
class HeadFitConfig:
    """How the head is fitted. The fit is deterministic (full-batch L-BFGS from the untrained head of the declared
    recipe), so there is no seed or learning rate."""

    max_epochs: int = 200
    """Most L-BFGS iterations (each one full pass over the cached training rows)."""
    patience: int = 10
    """Stop after this many iterations without a lower validation NLL."""
    whiten_floor: float = 1e-2
    """The fit runs in whitened node-state coordinates; covariance eigenvalues below this fraction of the largest are
    raised to it (a larger floor damps the directions in which the training states hardly vary). 1e-2 had the lowest
    validation NLL of 1e-6, 1e-3, 1e-2, 1e-1 for MESRNN on zara1 (validation windows only)."""
    data_dir: str | None = None
    """ETH/UCY folder (default: the usual search order)."""
    max_windows: int = 0
    """Use only the first N training and N validation windows (0 = all); for smoke tests."""
    batch_windows: int = 64
    """Windows per rollout batch when caching the node states."""

    def __post_init__(self) -> None:
        for name in ("max_epochs", "patience", "batch_windows"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if not 0.0 < self.whiten_floor <= 1.0:
            raise ConfigError(f"whiten_floor must lie in (0, 1], got {self.whiten_floor!r}")
        if self.max_windows < 0:
            raise ConfigError(f"max_windows must be >= 0, got {self.max_windows!r}")


@dataclass(frozen=True)
class HeadRows:
    """The cached inputs of the head: one row per pedestrian and predicted step of the mean rollout.

    Attributes:
        states: ``(R, node_hidden)`` float32 node states the head reads for the row's prediction.
        error: ``(R, 2)`` float32 true position minus the mean, normalised units.
        ahead: ``(R,)`` int64 steps after the last observed input (0 … ``PRED_LEN − 1``), the index of ``step_bias``.
    """

    states: torch.Tensor
    error: torch.Tensor
    ahead: torch.Tensor

    def __len__(self) -> int:
        return int(self.ahead.shape[0])


class _NodeStateTap(StructuralRNN):
    """A point network whose "distribution head" returns the node state itself, so the rollout's raw output
    (:meth:`StructuralRNN.forward_distribution`) is ``(B, T−1, N, node_hidden)`` node states aligned with the
    predictions, computed by the very code path that the gaussian head uses; the means are the point network's."""

    def __init__(self, point: StructuralRNN) -> None:
        super().__init__(replace(point.cfg, head="gaussian"))
        del self.scale_head
        del self.step_bias
        self.register_buffer("step_bias", torch.zeros(PRED_LEN, point.cfg.node_hidden), persistent=False)
        self.load_state_dict(point.state_dict())
        self.eval()

    def _head_linear(self, node_h: torch.Tensor) -> torch.Tensor:
        return node_h


@torch.no_grad()
def head_rows(
    point: StructuralRNN, norm: MinMax, windows: Sequence[Window], rows: str, batch_windows: int = 64
) -> HeadRows:
    """Roll ``point`` out on ``windows`` (the means fed back, as in evaluation) and keep the head's inputs.

    Args:
        point: a network with the point head (its weights are not modified).
        norm: the split's normalisation (that of the weights).
        rows: ``valid``: every pedestrian rolled out whose true position is known at the step (the rows of the
            training loss, :func:`crowdnav_mesrnn.training.trainer.gaussian_nll_loss`); ``scored``: the pedestrians present
            in all 20 steps (the rows of validation and evaluation, :func:`crowdnav_mesrnn.evaluation.metrics.collect_forecasts`).
    """
    if rows not in ("valid", "scored"):
        raise ValueError(f"rows must be 'valid' or 'scored', got {rows!r}")
    tap = _NodeStateTap(point)
    parts: dict[str, list[torch.Tensor]] = {"states": [], "error": [], "ahead": []}
    for chunk in batches(windows, batch_windows):
        pos, pres, scored = collate([windows[i] for i in chunk])
        pos_t, mask_t = torch.from_numpy(pos), torch.from_numpy(pres)
        normed = torch.where(mask_t.unsqueeze(-1), norm.normalise(pos_t), torch.zeros_like(pos_t))
        pred, states, used = tap.forward_distribution(normed, mask_t, OBS_LEN, teacher_forcing=False)
        assert states is not None
        if rows == "valid":
            keep = used[:, OBS_LEN - 1 :] & mask_t[:, OBS_LEN:]
        else:
            keep = torch.from_numpy(scored)[:, None, :].expand(-1, PRED_LEN, -1)
        ahead = torch.arange(PRED_LEN)[None, :, None].expand_as(keep)
        parts["states"].append(states[:, OBS_LEN - 1 :][keep].float())
        parts["error"].append((normed[:, OBS_LEN:] - pred[:, OBS_LEN - 1 :])[keep].float())
        parts["ahead"].append(ahead[keep])
    if not parts["ahead"]:
        raise ValueError("no windows to fit the head on")
    return HeadRows(*(torch.cat(parts[k]) for k in ("states", "error", "ahead")))


def metres_offset(norm: MinMax) -> float:
    """What turns an NLL in normalised units into one in metres: ``−ln(sx sy)`` with ``s`` the normalised units per
    metre (errors and scales scale alike, so the Mahalanobis term is unchanged)."""
    return -float(np.log(norm.scale).sum())


def _whitening(states: torch.Tensor, floor: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mu (H,), P (H, H))`` float64 with ``z = (h − mu) Pᵀ`` of unit covariance over ``states (R, H)`` (eigenvalues
    below ``floor`` times the largest are raised to it). Node states vary over ~1e-3 in some directions and ~1e-8 in
    others, so the head's own coordinates are badly conditioned; the fit runs in ``z`` and maps back exactly."""
    x = states.double()
    mu = x.mean(0)
    ev, vec = torch.linalg.eigh(torch.cov(x.T))
    return mu, (vec / ev.clamp(min=floor * float(ev.max())).sqrt()).T


def fit_head_on_rows(
    net: StructuralRNN,
    train: HeadRows,
    val: HeadRows,
    cfg: HeadFitConfig,
    nll_offset: float = 0.0,
    log: Callable[[str], None] | None = None,
) -> list[dict[str, float]]:
    """Fit ``net``'s head parameters (only those) to the training rows' mean NLL by L-BFGS (``scipy.optimize``,
    float64, in whitened node-state coordinates mapped back exactly to the head's ``Linear``); each iteration is one
    full pass over the rows (an "epoch" of the history). Keeps the iteration of lowest validation NLL (``val_nll``:
    mean over the validation rows plus ``nll_offset``) and stops after ``cfg.patience`` iterations without a lower one
    or at ``cfg.max_epochs``; epoch 0 is the head as given. Returns the history; ``net`` holds the selected head."""
    from scipy.optimize import minimize

    if not net.head_parameters():
        raise ValueError("the network has no distribution head to fit")
    mu, proj = _whitening(train.states, cfg.whiten_floor)
    z_train, z_val = (train.states.double() - mu) @ proj.T, (val.states.double() - mu) @ proj.T
    e_train, e_val = train.error.double(), val.error.double()
    h = z_train.shape[1]
    with torch.no_grad():  # the given head in whitened coordinates: W' = W P⁻¹ with b' = b + W mu
        w0 = net.scale_head.weight.double() @ torch.linalg.pinv(proj)
        b0 = net.scale_head.bias.double() + net.scale_head.weight.double() @ mu
        theta0 = torch.cat([w0.flatten(), b0, net.step_bias.double().flatten()]).numpy()

    def unpack(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return theta[: 3 * h].view(3, h), theta[3 * h : 3 * h + 3], theta[3 * h + 3 :].view(-1, 3)

    def mean_nll(theta: torch.Tensor, z: torch.Tensor, err: torch.Tensor, ahead: torch.Tensor) -> torch.Tensor:
        w, b, sb = unpack(theta)
        sigma, rho = params_from_raw(z @ w.T + b + sb[ahead])
        return gaussian.nll(err, sigma, rho).mean()

    def objective(theta_np: np.ndarray) -> tuple[float, np.ndarray]:
        theta = torch.from_numpy(theta_np).requires_grad_(True)
        loss = mean_nll(theta, z_train, e_train, train.ahead)
        loss.backward()
        assert theta.grad is not None
        return float(loss.detach()), theta.grad.numpy().copy()

    def val_nll(theta_np: np.ndarray) -> float:
        with torch.no_grad():
            return float(mean_nll(torch.from_numpy(theta_np), z_val, e_val, val.ahead)) + nll_offset

    best = {"val": val_nll(theta0), "theta": theta0, "epoch": 0, "since": 0}
    history: list[dict[str, float]] = [
        {"epoch": 0, "train_nll": objective(theta0)[0] + nll_offset, "val_nll": best["val"]}
    ]

    def callback(intermediate_result: Any) -> None:
        theta, epoch = np.asarray(intermediate_result.x), len(history)
        v = val_nll(theta)
        history.append({"epoch": epoch, "train_nll": float(intermediate_result.fun) + nll_offset, "val_nll": v})
        if log is not None:
            log(
                f"  epoch {epoch}: train NLL {history[-1]['train_nll']:.4f}, val NLL {v:.4f}{' *' if v < best['val'] else ''}"
            )
        if v < best["val"]:
            best.update(val=v, theta=theta.copy(), epoch=epoch, since=0)
        else:
            best["since"] += 1
            if best["since"] >= cfg.patience:
                raise StopIteration

    minimize(objective, theta0, jac=True, method="L-BFGS-B", callback=callback, options={"maxiter": cfg.max_epochs})
    w, b, sb = unpack(torch.from_numpy(best["theta"]))
    with torch.no_grad():  # back to the head's coordinates: W = W' P, b = b' − W' P mu
        weight = w @ proj
        net.scale_head.weight.copy_(weight.float())
        net.scale_head.bias.copy_((b - weight @ mu).float())
        net.step_bias.copy_(sb.float())
    history[0]["selected_epoch"] = best["epoch"]
    return history


def gaussian_network(point: StructuralRNN) -> StructuralRNN:
    """A network with the point weights and an untrained gaussian head (``scale_detach``, as the declared recipe)."""
    net = StructuralRNN(replace(point.cfg, head="gaussian", scale_detach=True))
    missing, unexpected = net.load_state_dict(point.state_dict(), strict=False)
    if unexpected or sorted(missing) != sorted(HEAD_KEYS):
        raise CheckpointError(
            f"point weights do not fit the gaussian network: missing {missing}, unexpected {unexpected}"
        )
    keep = set(map(id, net.head_parameters()))
    for p in net.parameters():
        p.requires_grad_(id(p) in keep)  # the trunk is frozen
    return net


def validation_nll_m(predictor: LearnedPredictor, windows: Sequence[Window]) -> float:
    """Validation NLL as training reports it (``Trainer.validate``): nats per position, metres, over every scored
    pedestrian and step, through the predictor's own distribution path."""
    scored = collect_forecasts(windows, distribution=predictor.predict_distribution_batch)
    assert scored.sigma is not None and scored.rho is not None
    return float(gaussian.nll(scored.error, scored.sigma, scored.rho).mean())


def fit_head(
    point_path: str | os.PathLike[str],
    dest: str | os.PathLike[str],
    cfg: HeadFitConfig = HeadFitConfig(),
    model: str | None = None,
    split: str | None = None,
    command: str = "",
    log: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Fit the gaussian head on the point weights at ``point_path`` (trunk frozen) and write the head-only file
    ``dest`` atomically (see the module docstring). Returns the record stored in the file (``head_fit``).

    Raises:
        FileNotFoundError: no point weights at ``point_path``.
        CheckpointError: they hold another model or split, or already a gaussian head.
    """
    point_path = Path(point_path)
    if not point_path.is_file():
        raise FileNotFoundError(
            f"no point weights at {point_path}: the head is fitted on them (train and export them first: "
            "`crowdnav-mesrnn predictor train` then `predictor export`)"
        )
    sha = file_sha256(point_path)
    ck: dict[str, Any] = torch.load(point_path, map_location="cpu", weights_only=True)
    if "base" in ck:
        raise CheckpointError(f"{point_path}: holds a fitted head, not point weights")
    point_pred = load_predictor(point_path, model=model, split=split)
    if point_pred.has_distribution:
        raise CheckpointError(f"{point_path}: holds a {point_pred.net.cfg.head} head; fit-head needs point weights")
    split = point_pred.split
    if split is None:
        raise CheckpointError(f"{point_path}: records no split (train_config.split); the head is fitted on its data")
    point, norm = point_pred.net, point_pred.norm
    train_w = split_windows(split, "train", int(ck["train_config"].get("min_scored", 2)), cfg.data_dir)
    val_w = split_windows(split, "val", 2, cfg.data_dir)
    if cfg.max_windows:
        train_w, val_w = train_w[: cfg.max_windows], val_w[: cfg.max_windows]
    train = head_rows(point, norm, train_w, "valid", cfg.batch_windows)
    val = head_rows(point, norm, val_w, "scored", cfg.batch_windows)
    net = gaussian_network(point)
    offset = metres_offset(norm)
    name = f"{point_pred.name}/{split}"
    if log is not None:
        log(f"{name}: {len(train_w)} train windows ({len(train)} rows), {len(val_w)} val windows ({len(val)} rows)")
    history = fit_head_on_rows(net, train, val, cfg, offset, log)
    fitted = LearnedPredictor(net, norm, split)
    val_nll = validation_nll_m(fitted, val_w)
    best_epoch = int(history[0]["selected_epoch"])
    cached = history[best_epoch]["val_nll"]
    if not abs(val_nll - cached) <= 1e-3 * max(1.0, abs(val_nll)):
        raise RuntimeError(f"{name}: the cached rows' val NLL {cached:.6f} differs from the rollout's {val_nll:.6f}")
    record = {
        "note": SHORTCUT_NOTE,
        "source": point_path.name,
        "source_sha256": sha,
        "config": {k: v for k, v in asdict(cfg).items() if k != "data_dir"},
        "train_windows": len(train_w),
        "train_rows": len(train),
        "val_windows": len(val_w),
        "val_rows": len(val),
        "epochs_run": len(history) - 1,
        "selected_epoch": best_epoch,
        "val_nll_m_before": history[0]["val_nll"],
        "val_nll_m": val_nll,
        "history": history,
        "command": command,
    }
    state = net.state_dict()
    payload = {
        "format": CHECKPOINT_FORMAT,
        "model_config": net.cfg.to_dict(),
        "train_config": ck["train_config"],
        "norm": ck["norm"],
        "epoch": ck.get("epoch"),
        "val": {**(ck.get("val") or {}), "val_nll_m": val_nll},
        "code_version": code_version(),
        "selection": {
            "note": SHORTCUT_NOTE,
            "source": point_path.name,
            "source_sha256": sha,
            "val_nll_m": val_nll,
            "head_epoch": best_epoch,
            "point_selection": ck.get("selection"),
        },
        "base": {"file": point_path.name, "sha256": sha},
        "head_fit": record,
        "state_dict": {k: state[k].detach().float().contiguous().clone() for k in HEAD_KEYS},
    }
    path = atomic_write(dest, lambda fh: torch.save(payload, fh))
    if log is not None:
        log(
            f"{name}: val NLL {record['val_nll_m_before']:.4f} -> {val_nll:.4f} nats per position (m), head epoch "
            f"{best_epoch} of {record['epochs_run']}; wrote {path} ({path.stat().st_size / 1e3:.1f} kB)"
        )
    return record
