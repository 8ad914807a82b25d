"""Without ``$CROWDNAV_MESRNN_DATA`` the tests needing ETH/UCY data skip, reported on one line saying how to get it."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_the_no_data_skips_are_reported_on_one_line(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "CROWDNAV_MESRNN_DATA"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    # two test modules with data tests at several places (each used to get a SKIPPED line of its own)
    files = ["tests/data/test_windows_and_splits.py", "tests/data/test_paths_and_cli.py"]
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-ra", "-p", "no:cacheprovider", *files],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout[-3000:]
    skipped = [line for line in done.stdout.splitlines() if line.startswith("SKIPPED")]
    assert len(skipped) == 1, skipped
    count = int(re.match(r"SKIPPED \[(\d+)\]", skipped[0]).group(1))  # type: ignore[union-attr]
    assert count == int(re.search(r"(\d+) skipped", done.stdout).group(1)) >= 3  # type: ignore[union-attr]
    assert "$CROWDNAV_MESRNN_DATA is not set" in skipped[0] and "export CROWDNAV_MESRNN_DATA=" in skipped[0]
