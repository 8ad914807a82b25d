"""Readable ablation plots: labels that do not collide, one legend outside the panels, a few fixed colours."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pytest
from matplotlib.text import Text

from agents.ablation.plots import DENSITY_ARMS, _edge, _label_points, write_plots

ROOT = Path(__file__).resolve().parents[3]


def _boxes_overlap(a, b) -> bool:  # type: ignore[no-untyped-def]
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_point_labels_do_not_collide() -> None:
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    points = [
        (0.50, 0.85, "mesrnn"),
        (0.51, 0.84, "cv"),
        (0.49, 0.845, "srnn"),
        (0.52, 0.85, "vlstm"),
        (0.0, 0.9, "oracle"),
    ]
    _label_points(ax, points)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [Text.get_window_extent(t, renderer) for t in ax.texts]  # the label, without its leader line
    assert len(boxes) == len(points)
    assert not any(_boxes_overlap(a, b) for i, a in enumerate(boxes) for b in boxes[i + 1 :])
    plt.close(fig)


def test_density_edges_are_labelled_as_whole_pedestrians() -> None:
    assert [_edge(v) for v in (0.0, 5.0, 23.0, 2.5)] == ["0", "5", "23", "2.5"]


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
def test_plots_of_the_committed_summary_have_one_legend_outside_the_panels(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    summary = json.loads((ROOT / "results" / "ablation" / "planning_aid" / "summary.json").read_text())
    figures = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))
    written = write_plots(summary, tmp_path)
    assert [Path(p).name for p in written] == ["rates_by_arm.png", "rates_vs_ade.png", "rates_by_density.png"]
    for fig in figures:
        assert len(fig.legends) == 1 and not any(ax.get_legend() for ax in fig.axes)
    density = figures[-1]
    labels = {t.get_text() for t in density.legends[0].get_texts()}
    assert labels == {"none", "cv", "mesrnn", "oracle"} and labels <= set(DENSITY_ARMS)  # four arms in fixed colours,
    # not ten (the committed grid has no uncertainty arms, which have colours of their own)
