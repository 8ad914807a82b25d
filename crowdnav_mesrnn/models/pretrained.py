"""The pretrained predictors shipped inside the package (one per model and leave-one-out split).

``crowdnav_mesrnn/pretrained/<model>_<split>.pt`` holds float32 weights, the model config, the train
config (with its split), the normalisation statistics fitted on that split's training data, and a
``selection`` note saying why this configuration was chosen (validation data only). Weights with the
distribution head (``head: gaussian``) ship beside them as ``<model>_gaussian_<split>.pt``; the point
weights are never replaced by them. ``predictor fit-head`` (:mod:`crowdnav_mesrnn.head_fit`) writes those files holding
only the head, fitted on the point weights beside them (named with their SHA-256, read by ``load_predictor``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from crowdnav_mesrnn.data.constants import SPLITS, check_split
from crowdnav_mesrnn.models.architecture import HEADS, MODEL_TYPES
from crowdnav_mesrnn.models.learned import CHECKPOINT_FORMAT, CheckpointError, LearnedPredictor, load_predictor
from crowdnav_mesrnn.utils import atomic_write

PRETRAINED_DIR = Path(__file__).resolve().parent.parent / "pretrained"


class PretrainedNotFoundError(FileNotFoundError):
    """The shipped weights for a model/split are missing."""


def pretrained_path(model: str, split: str, head: str = "point") -> Path:
    """Where the shipped weights of ``model``/``split`` with ``head`` (``point`` or ``gaussian``) live."""
    if model not in MODEL_TYPES:  # one weights file per architecture and split
        raise ValueError(f"unknown learned model {model!r}; valid: {', '.join(MODEL_TYPES)}")
    check_split(split)
    if head not in HEADS:
        raise ValueError(f"unknown head {head!r}; valid: {', '.join(HEADS)}")
    return PRETRAINED_DIR / (f"{model}_{split}.pt" if head == "point" else f"{model}_{head}_{split}.pt")


_CACHE: dict[tuple[str, str, str], LearnedPredictor] = {}


def load_pretrained(model: str, split: str, threads: int | None = None, head: str = "point") -> LearnedPredictor:
    """The shipped predictor ``model`` for ``split`` (trained without the split's test scene); ``head="gaussian"``
    loads the weights with the distribution head, shipped beside the point weights."""
    path = pretrained_path(model, split, head)
    if not path.is_file():
        how = (
            f"`crowdnav-mesrnn predictor train --model {model} --split {split}` and install with "
            f"`crowdnav-mesrnn predictor export runs/predictor/{model}_{split}/best.pt --model {model} --split {split}`"
            if head == "point"
            else f"`crowdnav-mesrnn predictor fit-head --model {model} --split {split}` (the head fitted on the point "
            "weights, trunk frozen), or the plan configs/predictor/gaussian.yaml (`crowdnav-mesrnn predictor plan "
            "configs/predictor/gaussian.yaml` then `--stage export`)"
        )
        raise PretrainedNotFoundError(
            f"no pretrained {model!r} weights with the {head} head for split {split!r} at {path}. Train them with {how}."
        )
    if threads is not None:
        torch.set_num_threads(threads)
    key = (model, split, head)
    if key not in _CACHE:
        pred = load_predictor(path, model=model, split=split)
        if pred.net.cfg.head != head:
            raise CheckpointError(f"{path}: holds a {pred.net.cfg.head} head, not {head}")
        _CACHE[key] = pred
    return _CACHE[key]


def available(head: str = "point") -> dict[str, list[str]]:
    """``model -> splits`` with shipped weights of ``head``."""
    return {m: [s for s in SPLITS if pretrained_path(m, s, head).is_file()] for m in MODEL_TYPES}


def export_checkpoint(
    checkpoint: str | os.PathLike[str], model: str, split: str, note: str = "", dest: Path | None = None
) -> Path:
    """Write a lean copy (float32 weights, configs, normalisation; no optimiser) of a trained checkpoint, by default
    to the shipped path of its head (:func:`pretrained_path`: a gaussian head never overwrites point weights)."""
    src = Path(checkpoint)
    head = load_predictor(src, model=model, split=split).net.cfg.head  # validates model, split and weights
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
    dest = dest or pretrained_path(model, split, head)
    return atomic_write(dest, lambda fh: torch.save(lean, fh))
