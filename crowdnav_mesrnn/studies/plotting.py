"""Figures like the paper's Fig. 7: observed paths, true futures and each model's forecast."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN
from crowdnav_mesrnn.data.windows import collate, split_windows
from crowdnav_mesrnn.evaluation.metrics import cv_predict_batch

COLOURS = {"cv": "tab:orange", "vlstm": "tab:purple", "srnn": "tab:blue", "mesrnn": "tab:red"}


def plot_window(
    split: str,
    index: int,
    out: str | os.PathLike[str] | None = None,
    models: Sequence[str] = ("cv", "vlstm", "srnn", "mesrnn"),
    data_dir: str | os.PathLike[str] | None = None,
) -> Path:
    """Draw test window ``index`` (among windows with >= 2 scored pedestrians) of ``split`` to scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    windows = split_windows(split, "test", min_scored=2, data_dir=data_dir)
    if not 0 <= index < len(windows):
        raise ValueError(f"window {index} out of range: split {split!r} has {len(windows)} test windows")
    w = windows[index]
    pos, pres, scored = collate([w])
    pos_t, pres_t = torch.from_numpy(pos), torch.from_numpy(pres)
    forecasts: dict[str, np.ndarray] = {}
    for name in models:
        if name == "cv":
            forecasts[name] = cv_predict_batch(pos_t, pres_t)[0].numpy()
        else:
            from crowdnav_mesrnn.models.pretrained import load_pretrained

            forecasts[name] = load_pretrained(name, split).predict_batch(pos_t, pres_t)[0].numpy()
    fig, ax = plt.subplots(figsize=(7, 7))
    for i in np.flatnonzero(scored[0]):
        obs = pos[0, :OBS_LEN, i]
        fut = pos[0, OBS_LEN - 1 :, i]
        ax.plot(obs[:, 0], obs[:, 1], "-", color="black", lw=1.5, label="observed" if i == 0 else None)
        ax.plot(fut[:, 0], fut[:, 1], "--", color="green", lw=1.5, label="true future" if i == 0 else None)
        for name, f in forecasts.items():
            path = np.concatenate([obs[-1:], f[:, i]], axis=0)
            ax.plot(path[:, 0], path[:, 1], ":", color=COLOURS.get(name, "grey"), lw=1.5)
    ctx = ~scored[0]
    for i in np.flatnonzero(ctx):
        m = pres[0, :, i]
        ax.plot(pos[0, m, i, 0], pos[0, m, i, 1], ".", color="lightgrey", ms=3)
    handles = [
        plt.Line2D([], [], color="black", label="observed (3.2 s)"),
        plt.Line2D([], [], color="green", ls="--", label="true future (4.8 s)"),
        *[plt.Line2D([], [], color=COLOURS.get(n, "grey"), ls=":", label=n.upper()) for n in forecasts],
        plt.Line2D([], [], color="lightgrey", marker=".", ls="", label="context pedestrians"),
    ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{split} test window {index} ({w.recording}, frame {w.start_frame}): {int(scored.sum())} scored")
    ax.grid(alpha=0.3)
    out = Path(out or f"docs/results/{split}_window_{index}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp.png")
    fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, out)
    return out
