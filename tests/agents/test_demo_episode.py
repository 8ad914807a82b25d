"""The demo's default episode: the rule of :mod:`agents.demo_episode` on known rows, and its result re-derived."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import agents.cli
from agents.demo_episode import DEMO_SEED, MIN_PATH_RATIO, choose, judge, table
from crowdnav_mesrnn.cli import main


def row(seed: int, outcome: str = "success", ratio: float | None = 1.3, density: float = 2.0, near: int = 5) -> dict:
    return {
        "seed": seed,
        "outcome": outcome,
        "path_ratio_required": ratio,
        "crowd_density": density,
        "pedestrians_near_path": near,
    }


def test_the_rule_keeps_visible_detours_that_succeed_and_takes_the_most_crowded() -> None:
    rows = [
        row(0, ratio=1.05, density=9.0),  # straight: dropped however crowded
        row(1, outcome="collision", density=8.0),  # a failure: dropped
        row(2, ratio=None, density=7.0),  # undefined ratio: dropped
        row(3, density=3.0),
        row(4, ratio=MIN_PATH_RATIO, density=4.0),  # at the threshold: kept
        row(5, density=2.0),
    ]
    candidates = judge(rows)
    assert [c.verdict for c in candidates] == [
        f"path ratio below {MIN_PATH_RATIO:g}",
        "not a success",
        f"path ratio below {MIN_PATH_RATIO:g}",
        "kept",
        "kept",
        "kept",
    ]
    assert choose(candidates) == 4
    assert "<- chosen" in table(candidates, 4).splitlines()[5]


def test_ties_go_to_more_pedestrians_near_the_path_then_to_the_smallest_seed() -> None:
    assert choose(judge([row(7, near=5), row(3, near=6), row(9, near=6)])) == 3
    assert choose(judge([row(0, outcome="timeout")])) is None


def test_the_demo_defaults_to_the_rules_seed_and_seed_overrides_it(capsys: pytest.CaptureFixture[str]) -> None:
    base = ["demo", "--policy", "straight", "--synthetic", "--predictor", "none", "--no-gif"]
    assert main(base) == 0
    assert f", seed {DEMO_SEED}," in capsys.readouterr().out.splitlines()[0]
    assert main([*base, "--seed", "3"]) == 0
    assert ", seed 3," in capsys.readouterr().out.splitlines()[0]


@pytest.mark.slow
def test_demo_seed_is_what_the_rule_chooses(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``crowdnav-mesrnn demo --choose-seed`` on the default configuration picks :data:`DEMO_SEED` (36 s to 2.5 min
    on a shared 2-core machine, computing the forecasts)."""
    if not agents.cli.SHIPPED_POLICY.is_file():
        pytest.fail(f"the shipped policy {agents.cli.SHIPPED_POLICY} is missing from the package")
    assert main(["demo", "--choose-seed", "--data-dir", str(data_dir)]) == 0
    out = capsys.readouterr().out
    assert "forecasts mesrnn" in out.splitlines()[0]  # the shipped configuration, not a fallback
    chosen = re.search(r"^chosen seed: (\d+)", out, flags=re.MULTILINE)
    assert chosen is not None, out
    assert int(chosen.group(1)) == DEMO_SEED
