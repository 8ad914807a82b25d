"""An evaluation's aggregates: rates and intervals on known inputs, the table, ``episodes.csv``."""

from __future__ import annotations

import csv
import json
import math
import re

import numpy as np
import pytest

from agents.evaluation.summary import OUTCOMES, episodes_csv, format_summary, summarise
from agents.rollout import ADDED_METRICS, EPISODE_COLUMNS, recorded_metrics


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval written out (an independent check of agents.stats through summarise)."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def hand_made_rows() -> list[dict]:
    outcomes = ["success"] * 7 + ["collision"] * 2 + ["timeout"]
    rows = []
    for i, outcome in enumerate(outcomes):
        rows.append(
            {
                "episode": i,
                "seed": 100 + i,
                "outcome": outcome,
                "navigation_time_s": 10.0 + i if outcome == "success" else 99.0,
                "path_ratio": 1.5,
                "min_gap_m": None if i == 9 else 0.1 * i,
                "forecast_ade_m": None,
                "steps": 20,
                "return": float(i),
            }
        )
    return rows


def test_summary_rates_have_wilson_intervals_and_counts() -> None:
    s = summarise(hand_made_rows())
    assert s["episodes"] == 10
    for name, k in (("success", 7), ("collision", 2), ("timeout", 1)):
        assert s[f"{name}_rate"] == pytest.approx(k / 10)
        assert s[f"{name}_count"] == k
        np.testing.assert_allclose(s[f"{name}_ci"], wilson(k, 10), rtol=1e-9)
    assert "successs" not in s and "timeouts" not in s
    json.dumps(s)  # JSON-ready


def test_the_table_names_every_line_by_its_key() -> None:
    """One naming scheme (issue 31): each line starts with the key of info["episode_metrics"] / episodes.csv (the
    JSON's ``<key>_mean``), then the value, the interval, the episodes used and the readable label."""
    rows = hand_made_rows()
    s = summarise(rows)
    s.update(policy="straight", split="zara1", predictor="none", crowd={"kind": "synthetic", "data_dir": None})
    lines = format_summary(s).splitlines()[2:]
    recorded = recorded_metrics(rows)
    assert len(lines) == len(OUTCOMES) + len(recorded)
    matches = [re.match(r"^  (\S+)(\s{2,})(-|-?\d+\.\d{3})", line) for line in lines]
    assert all(matches), lines
    assert {m.start(3) for m in matches if m} == {matches[0].start(3)}, "values start in one column"
    keys = [m.group(1) for m in matches if m]
    assert keys == [f"{o}_rate" for o in OUTCOMES] + list(recorded)
    assert all(f"{k}_mean" in s or (k.endswith("_rate") and k in s) for k in keys)  # every line is a key of the JSON
    nav = next(line for line in lines if line.startswith("  navigation_time_s "))
    assert "13.000" in nav and "navigation time, s; successes only" in nav


def test_metrics_added_since_a_file_was_written_are_absent_not_undefined() -> None:
    old = summarise(hand_made_rows())  # rows without the added metrics, as an archive written before them
    assert not any(k.startswith(m) for k in old for m in ADDED_METRICS)
    rows = hand_made_rows()
    for r in rows:
        r.update(spl=0.5 if r["outcome"] == "success" else 0.0, min_ttc_s=None)
    new = summarise(rows)
    assert new["spl_mean"] == pytest.approx(0.35) and new["spl_n"] == 10
    assert new["min_ttc_s_mean"] is None and new["min_ttc_s_n"] == 0  # recorded, undefined everywhere
    assert "mean_accel_mps2_mean" not in new  # still absent: no row has it


def test_a_signed_metric_keeps_its_interval_within_its_values() -> None:
    """min_gap_m is negative in a collision (overlap depth): its bootstrap interval may go below 0, never below the
    smallest value; min_clearance_m (0 at contact) never below 0."""
    gaps = [-0.5, 0.5, 0.5, 0.3, 0.2, 0.4, -0.2, 0.45, 0.35, 0.1]
    rows = [{"outcome": "success", "min_gap_m": g, "min_clearance_m": max(g, 0.0)} for g in gaps]
    s = summarise(rows)
    assert min(gaps) <= s["min_gap_m_ci"][0] <= s["min_gap_m_mean"] <= s["min_gap_m_ci"][1] <= max(gaps)
    assert 0.0 <= s["min_clearance_m_ci"][0]


def test_summary_means_use_the_episodes_each_metric_applies_to() -> None:
    s = summarise(hand_made_rows())
    # navigation time over the 7 successes only (10..16 s)
    assert s["navigation_time_s_mean"] == pytest.approx(13.0) and s["navigation_time_s_n"] == 7
    lo, hi = s["navigation_time_s_ci"]
    assert 10.0 <= lo < 13.0 < hi <= 16.0
    # a constant metric: a point interval
    assert s["path_ratio_mean"] == pytest.approx(1.5) and s["path_ratio_ci"] == [1.5, 1.5]
    # undefined values are left out; a metric defined nowhere has no mean
    assert s["min_gap_m_n"] == 9 and s["min_gap_m_mean"] == pytest.approx(0.4)
    assert s["forecast_ade_m_mean"] is None and s["forecast_ade_m_ci"] is None and s["forecast_ade_m_n"] == 0
    assert s["return_mean"] == pytest.approx(4.5)
    assert summarise([])["episodes"] == 0


def test_episodes_csv_has_the_interface_columns() -> None:
    text = episodes_csv(hand_made_rows())
    rows = list(csv.DictReader(text.splitlines()))
    assert list(rows[0]) == list(EPISODE_COLUMNS)
    assert rows[9]["min_gap_m"] == "" and rows[0]["outcome"] == "success"


def test_summary_counts_popin_episodes_and_events() -> None:
    rows = hand_made_rows()
    for row, events in zip(rows, [0, 2, 0, 1, 0, 0, 0, 0, 0, 0], strict=True):
        row["popin_events"] = events
    s = summarise(rows)
    assert s["popin_episodes"] == 2 and s["popin_events"] == 3
    assert "popin_events" in EPISODE_COLUMNS


def test_a_summary_on_validation_episodes_does_not_call_them_held_out() -> None:
    """``--episodes-from val`` replays the training scenes' validation period: the printed summary must not read
    "held-out scene" (the text a reader takes for a result)."""
    base = {**summarise([]), "policy": "planner", "predictor": "cv", "split": "univ", "episodes": 0, "seconds": 0.0}
    base["crowd"] = {"kind": "replay", "data_dir": "/data"}
    test = format_summary({**base, "env": {"part": "test", "episode_time": "all"}}).splitlines()[0]
    val = format_summary({**base, "env": {"part": "train", "episode_time": "val"}}).splitlines()[0]
    assert "held-out scene" in test
    assert "held-out scene" not in val and "validation period" in val and "NOT a held-out result" in val
