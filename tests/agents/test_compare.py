"""Paired comparison of evaluations on the same episodes (against folders and grid cells)."""

from __future__ import annotations

import csv
import gzip
import json
from pathlib import Path

import pytest

from agents.compare import grid_successes, main, paired


def _evaluation(folder: Path, outcomes: list[str], split: str = "univ") -> Path:
    folder.mkdir(parents=True)
    with open(folder / "episodes.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["episode", "outcome"])
        w.writeheader()
        w.writerows({"episode": i, "outcome": o} for i, o in enumerate(outcomes))
    (folder / "summary.json").write_text(json.dumps({"split": split, "predictor": "mesrnn"}))
    return folder


def test_pairs_on_common_episodes_with_mcnemar(tmp_path: Path) -> None:
    a = {i: i < 30 for i in range(40)}  # 30 of 40
    b = {i: i < 10 for i in range(20, 60)}  # on episodes 20..39: none of b's successes (b's are 0..9, not held)
    r = paired(a, b)
    assert r["a"]["episodes"] == 20 and r["a"]["successes"] == 10 and r["b"]["successes"] == 0
    assert r["difference"] == pytest.approx(0.5)
    assert r["p_value"] == pytest.approx(2 * 0.5**10)  # 10 discordant pairs, all one way
    with pytest.raises(ValueError, match="none in common"):
        paired({1: True}, {2: True})


def test_grid_cells_and_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    grid = tmp_path / "episodes.csv.gz"
    with gzip.open(grid, "wt", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["policy", "arm", "split", "seed", "episode", "outcome"])
        w.writeheader()
        for seed in ("0", "1"):
            for i in range(4):
                w.writerow({"policy": "ppo", "arm": "mesrnn", "split": "univ", "seed": seed, "episode": i,
                            "outcome": "success" if (i < 2) == (seed == "0") else "collision"})  # fmt: skip
    assert grid_successes(grid, "ppo/mesrnn/0", "univ") == {0: True, 1: True, 2: False, 3: False}
    with pytest.raises(ValueError, match="no episodes"):
        grid_successes(grid, "ppo/oracle", "univ")
    mine = _evaluation(tmp_path / "mine", ["success", "success", "collision", "success"])
    assert main([str(mine), "--grid", str(grid), "--cells", "ppo/mesrnn/0", "ppo/mesrnn/1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)[str(mine)]
    assert out["alone"]["successes"] == 3
    assert out["against"]["grid ppo/mesrnn/0"]["difference"] == pytest.approx(0.25)
    assert out["against"]["grid ppo/mesrnn/1"]["difference"] == pytest.approx(0.25)
    assert main([str(mine), "--cells", "ppo/mesrnn"]) == 2  # cells without a grid file


def test_grid_cells_from_a_results_folder_in_either_archive_layout(tmp_path: Path) -> None:
    from agents.ablation.archive import archive_files, write_archive

    header = ("policy", "arm", "split", "seed", "episode", "outcome")
    rows = [[policy, "cv", "univ", "", i, "success" if i < k else "collision"] for policy, k in (("a", 1), ("b", 3))
            for i in range(4)]  # fmt: skip
    files = archive_files(header, rows)
    write_archive(tmp_path / "new", files, out=lambda s: None)
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "episodes.csv.gz").write_bytes(files["b.csv.gz"])  # an older single file (of one policy)
    for grid in (tmp_path / "new", tmp_path / "new" / "episodes", tmp_path / "new" / "episodes" / "b.csv.gz"):
        assert grid_successes(grid, "b/cv", "univ") == {0: True, 1: True, 2: True, 3: False}, grid
    assert grid_successes(tmp_path / "old", "b/cv", "univ") == {0: True, 1: True, 2: True, 3: False}
    assert grid_successes(tmp_path / "new", "a/cv", "univ") == {0: True, 1: False, 2: False, 3: False}
    with pytest.raises(FileNotFoundError, match="holds no episode archive"):
        grid_successes(tmp_path, "a/cv", "univ")
