"""The pretrained predictors shipped inside the package (one per model and leave-one-out split).

``crowdnav_mesrnn/pretrained/<model>_<split>.pt`` holds float32 weights, the model config, the train
config (with its split), the normalisation statistics fitted on that split's training data, and a
``selection`` note saying why this configuration was chosen (validation data only).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from crowdnav_mesrnn.data.constants import SPLITS, check_split
from crowdnav_mesrnn.models.base import LEARNED_MODELS
from crowdnav_mesrnn.models.learned import CHECKPOINT_FORMAT, CheckpointError, LearnedPredictor, load_predictor
from crowdnav_mesrnn.utils import atomic_write

PRETRAINED_DIR = Path(__file__).resolve().parent.parent / "pretrained"


class PretrainedNotFoundError(FileNotFoundError):
    """The shipped weights for a model/split are missing."""


def pretrained_path(model: str, split: str) -> Path:
    if model not in LEARNED_MODELS:
        raise ValueError(f"unknown learned model {model!r}; valid: {', '.join(LEARNED_MODELS)}")
    check_split(split)
    return PRETRAINED_DIR / f"{model}_{split}.pt"


_CACHE: dict[tuple[str, str], LearnedPredictor] = {}


def load_pretrained(model: str, split: str, threads: int | None = None) -> LearnedPredictor:
    """The shipped predictor ``model`` for ``split`` (trained without the split's test scene)."""
    path = pretrained_path(model, split)
    if not path.is_file():
        raise PretrainedNotFoundError(
            f"no pretrained {model!r} weights for split {split!r} at {path}. Train them with "
            f"`crowdnav-mesrnn predictor train --model {model} --split {split}` and install with "
            f"`crowdnav-mesrnn predictor export runs/predictor/{model}_{split}/best.pt --model {model} --split {split}`."
        )
    if threads is not None:
        torch.set_num_threads(threads)
    key = (model, split)
    if key not in _CACHE:
        _CACHE[key] = load_predictor(path, model=model, split=split)
    return _CACHE[key]


def available() -> dict[str, list[str]]:
    """``model -> splits`` with shipped weights."""
    return {m: [s for s in SPLITS if pretrained_path(m, s).is_file()] for m in LEARNED_MODELS}


def export_checkpoint(
    checkpoint: str | os.PathLike[str], model: str, split: str, note: str = "", dest: Path | None = None
) -> Path:
    """Write a lean copy (float32 weights, configs, normalisation; no optimiser) of a trained checkpoint."""
    src = Path(checkpoint)
    load_predictor(src, model=model, split=split)  # validates model, split and weights
    ck: dict[str, Any] = torch.load(src, map_location="cpu", weights_only=True)
    lean = {
        "format": CHECKPOINT_FORMAT,
        "model_config": ck["model_config"],
        "train_config": ck["train_config"],
        "norm": ck["norm"],
        "epoch": ck.get("epoch"),
        "val": ck.get("val"),
        "code_version": ck.get("code_version"),
        "selection": {"note": note, "source": str(src), "val": ck.get("val"), "epoch": ck.get("epoch")},
        "state_dict": {k: v.detach().float().contiguous().clone() for k, v in ck["state_dict"].items()},
    }
    if lean["train_config"].get("split") != split:
        raise CheckpointError(f"{src}: trained for split {lean['train_config'].get('split')!r}, not {split!r}")
    dest = dest or pretrained_path(model, split)
    return atomic_write(dest, lambda fh: torch.save(lean, fh))
