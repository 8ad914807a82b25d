"""Data folder resolution, the checksum check and the ``data`` CLI."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data import ENV_VAR, EXPECTED_TEST_WINDOWS, DataNotFoundError, check_data_dir, find_data_dir


def make_data_dir(root: Path) -> Path:
    (root / "all_data").mkdir(parents=True)
    f = root / "all_data" / "crowds_zara01.txt"
    f.write_text("10\t1\t1.0\t2.0\n20\t1\t1.5\t2.0\n")
    digest = hashlib.sha256(f.read_bytes()).hexdigest()
    (root / "SHA256SUMS").write_text(f"{digest}  all_data/crowds_zara01.txt\n")
    return root


def test_resolution_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    a, b = make_data_dir(tmp_path / "a"), make_data_dir(tmp_path / "b")
    monkeypatch.setenv(ENV_VAR, str(b))
    assert find_data_dir(a) == a
    assert find_data_dir() == b
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    with pytest.raises(DataNotFoundError) as info:
        find_data_dir()
    msg = str(info.value)
    assert "working directory" in msg and "user cache" in msg and ENV_VAR in msg
    c = make_data_dir(tmp_path / "data" / "eth_ucy")
    assert find_data_dir() == c


def test_wrong_explicit_dir_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV_VAR, str(make_data_dir(tmp_path / "good")))
    with pytest.raises(DataNotFoundError, match="argument"):
        find_data_dir(tmp_path / "typo")


def test_check_detects_corruption_and_bad_format(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = make_data_dir(tmp_path / "d")
    assert check_data_dir(root).ok
    assert main(["data", "check", str(root)]) == 0
    (root / "all_data" / "crowds_zara01.txt").write_text("10\t1\t1.0\n")
    report = check_data_dir(root)
    assert not report.ok
    assert any("checksum mismatch" in p for p in report.problems)
    assert any("crowds_zara01.txt:1: expected 4 columns" in p for p in report.problems)
    assert main(["data", "check", str(root)]) == 1


def test_summary_json_reproduces_window_counts(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "summary", "--json", "--data-dir", str(data_dir)]) == 0
    out = json.loads(capsys.readouterr().out)
    for split, n in EXPECTED_TEST_WINDOWS.items():
        assert out["splits"][split]["test"]["windows_min2"] == n
    assert out["recordings"]["biwi_eth"]["step_s"] == pytest.approx(0.6667, abs=1e-3)


def test_cli_reports_missing_data(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "summary", "--data-dir", str(tmp_path / "nowhere")]) == 2
    assert "no ETH/UCY data found" in capsys.readouterr().err


def test_check_of_a_folder_without_data_files_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "eth_ucy"
    empty.mkdir()
    report = check_data_dir(empty)
    assert not report.ok and report.checked == 0
    assert main(["data", "check", str(empty)]) == 1
    captured = capsys.readouterr()
    assert f"{empty}: no data files" in captured.err and "OK" not in captured.out
    (empty / "notes.md").write_text("not data\n")
    assert main(["data", "check", str(empty)]) == 1
