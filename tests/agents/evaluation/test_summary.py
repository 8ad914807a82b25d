"""An evaluation's aggregates: rates and intervals on known inputs, the table, ``episodes.csv``."""

from __future__ import annotations

import csv
import json
import math
import re

import numpy as np
import pytest

from agents.evaluation.summary import OUTCOMES, episodes_csv, format_summary, summarise
from agents.rollout import EPISODE_COLUMNS, METRICS


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


def test_the_table_separates_every_label_from_its_value() -> None:
    s = summarise(hand_made_rows())
    s.update(policy="straight", split="zara1", predictor="none", crowd={"kind": "synthetic", "data_dir": None})
    lines = format_summary(s).splitlines()[1:]
    assert len(lines) == len(OUTCOMES) + len(METRICS)
    matches = [re.match(r"^  (\S.*?\S)(\s{2,})(-|-?\d+\.\d{3})", line) for line in lines]
    assert all(matches), lines
    assert {m.start(3) for m in matches if m} == {matches[0].start(3)}, "values start in one column"
    assert ("navigation_time_s (successes)", "13.000") in {(m.group(1), m.group(3)) for m in matches if m}


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
