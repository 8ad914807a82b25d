"""Learning curves: validation history of a run folder, its Wilson intervals, the plot and the CSV."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import pytest

from agents.curves import curves_csv, main, merge_curves, plot_curves, read_curve, read_curves_csv
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


def test_a_table_reads_back_as_its_curves_and_merges_with_run_folders(tiny_ppo_run: Path, tmp_path: Path) -> None:
    run = read_curve(tiny_ppo_run)
    table = tmp_path / "curves.csv"
    table.write_text(curves_csv([run, read_curve(tiny_ppo_run, label="again")]))
    back = read_curves_csv(table)
    assert [c.label for c in back] == ["none s0", "again"] and {str(c.run) for c in back} == {str(tiny_ppo_run)}
    assert (back[0].predictor, back[0].split, back[0].seed) == (run.predictor, run.split, run.seed)
    for a, b in zip(back[0].points, run.points, strict=True):  # every column of the table, exactly (repr round trip)
        assert {k: a[k] for k in a} == {k: b[k] for k in a}
    assert set(back[0].points[0]) >= {"step", "episodes", "success_rate", "success_lo", "success_hi"}
    other = tmp_path / "other"
    shutil.copytree(tiny_ppo_run, other)
    merged = merge_curves(read_curves_csv(table)[:1], [read_curve(other), read_curve(tiny_ppo_run, label="new")])
    assert [c.label for c in merged] == ["new", "none s0"] and merged[1].run == other  # replaced in place, then added
    both = merge_curves(back, [read_curve(tiny_ppo_run, label="one")])  # a run's curves all replaced by the new
    assert [c.label for c in both] == ["one"]


def test_the_command_redraws_a_table_and_filters_by_arm(tiny_ppo_run: Path, tmp_path: Path) -> None:
    table = tmp_path / "curves.csv"
    assert main([str(tiny_ppo_run), "--out", str(tmp_path / "a.png"), "--csv", str(table)]) == 0
    first = table.read_text()
    # the table alone, written again: the same text (so a grid's committed table survives its run folders)
    assert main(["--from-csv", str(table), "--out", str(tmp_path / "b.png"), "--csv", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "b.csv").read_text() == first
    # and with the run folder given again: its rows replaced, not doubled
    assert main([str(tiny_ppo_run), "--from-csv", str(table), "--out", str(tmp_path / "c.png"), "--csv",
                 str(tmp_path / "c.csv")]) == 0  # fmt: skip
    assert (tmp_path / "c.csv").read_text() == first
    assert main(["--from-csv", str(table), "--predictor", "none", "--out", str(tmp_path / "d.png")]) == 0
    assert main(["--from-csv", str(table), "--predictor", "oracle", "--out", str(tmp_path / "e.png")]) == 2
    assert not (tmp_path / "e.png").exists()
    assert main(["--out", str(tmp_path / "f.png")]) == 2


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda t: t.replace(",mean_return", ",other"), r"missing column\(s\) \['mean_return'\]"),
        (lambda t: t.replace(",0,0.0,", ",zero,0.0,", 1), r"line 2: column 'seed' is 'zero'"),
        (lambda t: _field(t, 3, "success_rate", "nan"), r"line 3: column 'success_rate' is 'nan', not a finite"),
        (
            lambda t: _field(t, 3, "split", "eth"),
            r"line 3: run .* \('none', 'eth', 0\) here, \('none', 'zara1', 0\) above",
        ),
    ],
)
def test_a_malformed_table_is_refused_naming_its_line(tiny_ppo_run: Path, tmp_path: Path, edit, match) -> None:
    table = tmp_path / "curves.csv"
    table.write_text(edit(curves_csv([read_curve(tiny_ppo_run)])))
    with pytest.raises(ValueError, match=match):
        read_curves_csv(table)


def _field(text: str, line: int, column: str, value: str) -> str:
    """``text`` (a curves table) with ``column`` of file line ``line`` set to ``value``."""
    rows = list(csv.DictReader(io.StringIO(text)))
    rows[line - 2][column] = value
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()
