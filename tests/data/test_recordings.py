"""Parsing SGAN-format files: good files load, every kind of malformed file names file and line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.data import DataFormatError, parse_file

GOOD = "780.0\t1.0\t8.46\t3.59\n790.0\t1.0\t9.57\t3.79\n790.0\t2.0\t1.0\t2.0\n810.0\t2.0\t1.5\t2.5\n"


def write(tmp_path: Path, text: str, name: str = "crowds_zara01.txt") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_parse_good_file(tmp_path: Path) -> None:
    rec = parse_file(write(tmp_path, GOOD))
    assert rec.frames.tolist() == [780, 790, 810]
    assert rec.ped_ids.tolist() == [1, 2]
    assert rec.present.tolist() == [[True, False], [True, True], [False, True]]
    np.testing.assert_allclose(rec.positions[1, 0], [9.57, 3.79])
    assert rec.step_s == pytest.approx(0.4)
    # Frame gaps are real time: 810 is three steps after 780.
    np.testing.assert_allclose(rec.times_s(), [0.0, 0.4, 1.2])


def test_biwi_eth_step_time(tmp_path: Path) -> None:
    rec = parse_file(write(tmp_path, GOOD, "biwi_eth_train.txt"))
    assert rec.step_s == pytest.approx(10 / 15)
    assert rec.base_name == "biwi_eth"


@pytest.mark.parametrize(
    ("text", "line", "what"),
    [
        (GOOD + "820.0\t3.0\t1.0\n", 5, "expected 4 columns"),
        (GOOD + "820.0\t3.0\t1.0\t2.0\t5.0\n", 5, "expected 4 columns"),
        ("780.0\t1.0\tabc\t3.59\n", 1, "non-numeric"),
        (GOOD.replace("1.5\t2.5", "nan\t2.5"), 4, "NaN or infinite"),
        (GOOD.replace("1.5\t2.5", "1.5\tinf"), 4, "NaN or infinite"),
        (GOOD + "790.0\t1.0\t9.0\t3.0\n", 5, "duplicated row for frame 790, pedestrian 1 .first at line 2"),
        (GOOD + "820.5\t1.0\t9.0\t3.0\n", 5, "must be integers"),
        ("", 1, "empty file"),
        ("\n\n", 1, "empty file"),
    ],
)
def test_malformed_files_name_file_and_line(tmp_path: Path, text: str, line: int, what: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(DataFormatError, match=what) as info:
        parse_file(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}:{line}:"), msg
    assert "\n" not in msg
