"""Learning curves: validation history of a run folder, its Wilson intervals, the plot and the CSV."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import pytest

from agents.curves import curves_csv, main, plot_curves, read_curve
from agents.stats import wilson_interval


def test_a_run_validates_at_the_warm_start_and_after_and_records_intervals(tiny_ppo_run: Path) -> None:
    curve = read_curve(tiny_ppo_run)
    assert curve.predictor == "none" and curve.split == "zara1" and curve.seed == 0
    steps = [p["step"] for p in curve.points]
    assert steps[0] == 0 and steps == sorted(steps) and steps[-1] == 128
    for p in curve.points:
        assert p["episodes"] == 2
        assert (p["success_lo"], p["success_hi"]) == pytest.approx(wilson_interval(round(2 * p["success_rate"]), 2))


def test_histories_without_interval_columns_get_them_from_the_config(tiny_ppo_run: Path, tmp_path: Path) -> None:
    run = tmp_path / "old"
    shutil.copytree(tiny_ppo_run, run)
    text = (run / "evaluations.csv").read_text()
    rows = list(csv.DictReader(io.StringIO(text)))
    keep = ["step", "success_rate", "collision_rate", "timeout_rate", "mean_return", "seconds", "new_best"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keep, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    (run / "evaluations.csv").write_text(buf.getvalue())
    old, new = read_curve(run), read_curve(tiny_ppo_run)
    for a, b in zip(old.points, new.points, strict=True):
        assert (a["episodes"], a["success_lo"], a["success_hi"]) == pytest.approx(
            (b["episodes"], b["success_lo"], b["success_hi"])
        )


def test_plot_and_csv(tiny_ppo_run: Path, tmp_path: Path) -> None:
    curves = [read_curve(tiny_ppo_run), read_curve(tiny_ppo_run, label="again")]
    out = plot_curves(curves, tmp_path / "curves.png", title="pytest")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader(io.StringIO(curves_csv(curves))))
    assert len(rows) == 2 * len(curves[0].points) and {r["label"] for r in rows} == {"none s0", "again"}
    assert main([str(tiny_ppo_run), "--out", str(tmp_path / "c.svg"), "--csv", str(tmp_path / "c.csv")]) == 0
    assert (tmp_path / "c.svg").read_text().lstrip().startswith("<?xml")
    assert main([str(tiny_ppo_run), "--out", str(tmp_path / "x.png"), "--labels", "a", "b"]) == 2


def test_a_folder_without_validations_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"evaluations\.csv"):
        read_curve(tmp_path)
