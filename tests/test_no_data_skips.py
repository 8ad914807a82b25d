"""The tests find the ETH/UCY data exactly where the project does (``$CROWDNAV_MESRNN_DATA``, ``./data/eth_ucy``,
``~/.cache/crowdnav-mesrnn/eth_ucy``), and skip only when none holds it, on one line naming the places searched and
how to get the data."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _pytest(args: list[str], home: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``python -m pytest ARGS`` in a fresh interpreter without ``$CROWDNAV_MESRNN_DATA``, with ``HOME`` at ``home``
    (so the user cache searched is ``home/.cache/crowdnav-mesrnn/eth_ucy``), run from ``cwd``."""
    env = {k: v for k, v in os.environ.items() if k != "CROWDNAV_MESRNN_DATA"}
    env["HOME"] = str(home)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-ra", "-p", "no:cacheprovider", f"--rootdir={REPO}", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_recording_loads(data_dir: Path) -> None:
    """A tiny data test, run below in a subprocess that finds the data only in the user cache."""
    from crowdnav_mesrnn.data import load_recording

    rec = load_recording("crowds_zara01")
    assert rec.positions.shape[0] == len(rec.frames) > 0
    assert data_dir.is_dir()


@pytest.mark.slow
def test_the_data_in_the_user_cache_is_found_without_the_variable(data_dir: Path, tmp_path: Path) -> None:
    """After ``crowdnav-mesrnn data download`` (which installs into ``~/.cache/crowdnav-mesrnn/eth_ucy``) the data
    tests run, with ``$CROWDNAV_MESRNN_DATA`` unset."""
    cache = tmp_path / "home" / ".cache" / "crowdnav-mesrnn"
    cache.mkdir(parents=True)
    (cache / "eth_ucy").symlink_to(data_dir.resolve(), target_is_directory=True)
    node = f"{Path(__file__).relative_to(REPO)}::test_a_recording_loads"
    done = _pytest([node], home=tmp_path / "home", cwd=REPO)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert re.search(r"\b1 passed\b", done.stdout) and "skipped" not in done.stdout, done.stdout[-3000:]


@pytest.mark.slow
def test_the_no_data_skips_are_reported_on_one_line(tmp_path: Path) -> None:
    if (REPO / "data" / "eth_ucy" / "all_data").is_dir():
        pytest.skip("this checkout holds ./data/eth_ucy: the project finds data there, so nothing skips")
    home = tmp_path / "empty-home"
    home.mkdir()
    # two test modules with data tests at several places (each used to get a SKIPPED line of its own)
    files = ["tests/data/test_windows_and_splits.py", "tests/data/test_paths_and_cli.py"]
    done = _pytest(files, home=home, cwd=REPO)
    assert done.returncode == 0, done.stdout[-3000:]
    skipped = [line for line in done.stdout.splitlines() if line.startswith("SKIPPED")]
    assert len(skipped) == 1, skipped
    count = int(re.match(r"SKIPPED \[(\d+)\]", skipped[0]).group(1))  # type: ignore[union-attr]
    assert count == int(re.search(r"(\d+) skipped", done.stdout).group(1)) >= 3  # type: ignore[union-attr]
    line = skipped[0]
    # the places searched, in the project's order, and how to get the data
    assert "no ETH/UCY data found" in line and "$CROWDNAV_MESRNN_DATA (not set)" in line
    assert str(REPO / "data" / "eth_ucy") in line and str(home / ".cache" / "crowdnav-mesrnn" / "eth_ucy") in line
    assert "crowdnav-mesrnn data download" in line and "export CROWDNAV_MESRNN_DATA=" in line
