"""``crowdnav_mesrnn.utils``: the file lock shared by the predictor plan and the forecast cache."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from crowdnav_mesrnn.utils import file_lock


@pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")
def test_file_lock_excludes_a_second_holder_until_released(tmp_path: Path) -> None:
    path = tmp_path / "x.lock"
    with file_lock(path) as first:
        assert first and path.exists()
        # flock belongs to the open file: a second open of the same file is a second holder.
        with file_lock(path, blocking=False) as second:
            assert second is False
    with file_lock(path, blocking=False) as again:
        assert again is True


def test_file_lock_reports_an_unwritable_place(tmp_path: Path) -> None:
    with pytest.raises(OSError), file_lock(tmp_path / "missing" / "x.lock"):
        pass
