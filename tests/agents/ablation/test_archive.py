"""agents.ablation.archive: the episode archive on disk, one gzipped CSV per policy, and the older single file.

Hand-made tables only: the summary's use of the archive (re-rendered byte for byte, the older file moved or left) is
tested with the grid in ``test_grid.py``.
"""

from __future__ import annotations

import csv
import gzip
import io
from pathlib import Path

import pytest

from agents.ablation.archive import (
    ARCHIVE_DIR,
    LEGACY_ARCHIVE,
    ArchiveConflict,
    archive_files,
    archive_name,
    archive_policy,
    read_rows,
    split_legacy,
    write_archive,
)
from agents.ablation.split_archive import main as split_main

HEADER = ("policy", "arm", "split", "seed", "episode", "outcome", "navigation_time_s")
#: Policies in the order of their names; ``PPO`` and ``ppo`` share a file name on a file system that ignores case
#: unless the encoding keeps them apart.
POLICIES = ("PPO", "planner@none", "planner@orca", "ppo", "search")


def _table(policies: tuple[str, ...] = POLICIES, episodes: int = 3) -> list[list[str]]:
    """Rows as the grid's archive lists them: by policy, then arm, then episode; a value at full float precision."""
    return [
        [policy, arm, "zara1", "", str(ep), "success" if ep % 2 else "collision", repr(10.123456789012345 + ep / 3)]
        for policy in sorted(policies)
        for arm in ("cv", "none")
        for ep in range(episodes)
    ]


def _dicts(rows: list[list[str]], header: tuple[str, ...] = HEADER) -> list[dict[str, str]]:
    return [dict(zip(header, row, strict=True)) for row in rows]


def _legacy(folder: Path, rows: list[list[str]], header: tuple[str, ...] = HEADER) -> Path:
    """The older single ``episodes.csv.gz`` of ``rows``."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / LEGACY_ARCHIVE).write_bytes(gzip.compress(buf.getvalue().encode("utf-8"), mtime=0))
    return folder / LEGACY_ARCHIVE


def _read(path: Path) -> list[dict[str, str]]:
    with gzip.open(path, "rt", newline="") as fh:
        return list(csv.DictReader(fh))


# ----------------------------------------------------------------------------- file names


@pytest.mark.parametrize(
    ("policy", "name"),
    [
        ("planner", "planner.csv.gz"),
        ("planner@orca", "planner@orca.csv.gz"),
        ("search_v2-dense.1", "search_v2-dense.1.csv.gz"),
        ("PPO", "%50%50%4F.csv.gz"),
        ("a/b", "a%2Fb.csv.gz"),
        ("a%2Fb", "a%252%46b.csv.gz"),
        ("a b", "a%20b.csv.gz"),
        (".hidden", "%2Ehidden.csv.gz"),
        ("naïve", "na%C3%AFve.csv.gz"),
        ("con", "%63on.csv.gz"),
        ("lpt1.x", "%6Cpt1.x.csv.gz"),
    ],
)
def test_file_names_are_the_policies_percent_encoded(policy: str, name: str) -> None:
    assert archive_name(policy) == name
    assert archive_policy(name) == policy


def test_file_names_are_one_to_one_even_ignoring_case_and_others_are_refused() -> None:
    policies = ["ppo", "PPO", "Ppo", "pPo", "a/b", "a%2Fb", "a%2fb", "con", "%63on", "x.", ".x", "x..y", "ß", "SS"]
    names = [archive_name(p) for p in policies]
    assert len({n.casefold() for n in names}) == len(policies)
    assert all(set(n) <= set("abcdefghijklmnopqrstuvwxyz0123456789_-@.%ABCDEF") for n in names), names
    for bad in ("ppo.csv", ".csv.gz", "%70po.csv.gz", "%4f.csv.gz", "%FF.csv.gz", "con.csv.gz", "a/b.csv.gz"):
        with pytest.raises(ValueError, match="not the archive file name of a policy"):
            archive_policy(bad)


# ----------------------------------------------------------------------------- writing and reading


def test_each_policy_goes_to_its_own_file(tmp_path: Path) -> None:
    rows = _table()
    files = archive_files(HEADER, rows)
    assert list(files) == [archive_name(p) for p in POLICIES]  # in the order of the policies' names
    write_archive(tmp_path, files, out=lambda s: None)
    assert sorted(p.name for p in (tmp_path / ARCHIVE_DIR).iterdir()) == sorted(files)
    for policy in POLICIES:
        with gzip.open(tmp_path / ARCHIVE_DIR / archive_name(policy), "rt", newline="") as fh:
            header, *held = list(csv.reader(fh))
        assert tuple(header) == HEADER  # the same header in every file
        assert held == [r for r in rows if r[0] == policy]  # all of this policy's rows, in their order, and no other


def test_the_split_archive_round_trips(tmp_path: Path) -> None:
    rows = _table()
    files = archive_files(HEADER, rows)
    assert archive_files(HEADER, rows) == files  # byte for byte for the same input
    write_archive(tmp_path, files, out=lambda s: None)
    assert read_rows(tmp_path) == _dicts(rows)  # every row, every value as written, in the table's order
    assert {p.name: p.read_bytes() for p in (tmp_path / ARCHIVE_DIR).iterdir()} == files
    assert not [p for p in tmp_path.iterdir() if p.name != ARCHIVE_DIR]  # no temporary folder or file left


def test_a_file_with_another_policys_rows_or_an_unknown_name_is_refused(tmp_path: Path) -> None:
    files = archive_files(HEADER, _table())
    write_archive(tmp_path, files, out=lambda s: None)
    target = tmp_path / ARCHIVE_DIR
    (target / "search.csv.gz").write_bytes(files["ppo.csv.gz"])
    with pytest.raises(ValueError, match=r"search\.csv\.gz: row 1 is of policy 'ppo'"):
        read_rows(tmp_path)
    (target / "search.csv.gz").write_bytes(files["search.csv.gz"])
    (target / "Search.csv.gz").write_bytes(files["search.csv.gz"])
    with pytest.raises(ValueError, match=r"'Search\.csv\.gz' is not the archive file name"):
        read_rows(tmp_path)


def test_the_older_single_file_is_read(tmp_path: Path) -> None:
    rows = _table()
    _legacy(tmp_path, rows)
    assert read_rows(tmp_path) == _dicts(rows)
    assert read_rows(tmp_path / "nothing here") == []


def test_both_layouts_that_disagree_raise_naming_both_files(tmp_path: Path) -> None:
    rows = _table()
    write_archive(tmp_path, archive_files(HEADER, rows), out=lambda s: None)
    _legacy(tmp_path, rows)
    assert read_rows(tmp_path) == _dicts(rows)  # the same rows twice: either will do
    changed = [list(r) for r in rows]
    changed[7][5] = "timeout"
    _legacy(tmp_path, changed)
    with pytest.raises(ArchiveConflict) as err:
        read_rows(tmp_path)
    assert f"{tmp_path / ARCHIVE_DIR}/" in str(err.value) and str(tmp_path / LEGACY_ARCHIVE) in str(err.value)
    assert "row 8 differs" in str(err.value)
    _legacy(tmp_path, rows[:-1])  # a row fewer
    with pytest.raises(ArchiveConflict, match=r"30 rows.*29 rows"):
        read_rows(tmp_path)


def test_the_older_file_is_removed_only_when_it_holds_the_new_files_rows(tmp_path: Path) -> None:
    rows = _table()
    lines: list[str] = []
    changed = [list(r) for r in rows]
    changed[7][5] = "timeout"  # a row the new files do not hold (rows[:-1] they all hold: that file is removed)
    for folder, old in (("same", rows), ("other", changed)):
        _legacy(tmp_path / folder, old)
        write_archive(tmp_path / folder, archive_files(HEADER, rows), out=lines.append)
    assert not (tmp_path / "same" / LEGACY_ARCHIVE).exists()
    assert (tmp_path / "other" / LEGACY_ARCHIVE).is_file()  # not the new files' rows: not this archive's, kept
    assert lines[0].startswith(f"removed {tmp_path / 'same' / LEGACY_ARCHIVE}")
    assert lines[1].startswith(f"warning: left {tmp_path / 'other' / LEGACY_ARCHIVE} as it is")
    # a file of a policy the new archive does not hold is left, and said
    write_archive(tmp_path / "same", archive_files(HEADER, _table(("planner@none",))), out=lines.append)
    assert (tmp_path / "same" / ARCHIVE_DIR / "search.csv.gz").is_file()
    assert lines[-1].startswith("warning: left 4 file(s)") and "search.csv.gz" in lines[-1]


# ----------------------------------------------------------------------------- moving an older archive


def test_an_older_archive_is_split_row_for_row(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    header = (*HEADER[:-1], "nav_time")  # an older archive's own columns and rounding stay as they are
    rows = [[*r[:-1], r[-1][:6]] for r in _table()]
    _legacy(tmp_path, rows, header)
    assert split_main([str(tmp_path)]) == 0
    assert f"{tmp_path / ARCHIVE_DIR}/: 5 file(s), the largest" in capsys.readouterr().out
    assert not (tmp_path / LEGACY_ARCHIVE).exists()
    assert read_rows(tmp_path) == _dicts(rows, header)
    assert split_main([str(tmp_path)]) == 0  # split already: said, and left (a glob of folders goes on)
    assert "split already" in capsys.readouterr().out
    assert read_rows(tmp_path) == _dicts(rows, header)
    assert split_main([str(tmp_path / "nothing here")]) == 2  # neither layout: nothing to split
    assert "does not exist" in capsys.readouterr().err


def test_an_older_archive_is_not_split_when_that_would_reorder_or_replace_rows(tmp_path: Path) -> None:
    rows = _table()
    _legacy(tmp_path / "unsorted", rows[::-1])
    with pytest.raises(ValueError, match="not in the order of their policies' names"):
        split_legacy(tmp_path / "unsorted")
    assert not (tmp_path / "unsorted" / ARCHIVE_DIR).exists()
    files = archive_files(HEADER, rows[1:])
    write_archive(tmp_path / "both", files, out=lambda s: None)
    _legacy(tmp_path / "both", rows)
    with pytest.raises(ArchiveConflict):
        split_legacy(tmp_path / "both")
    assert (tmp_path / "both" / LEGACY_ARCHIVE).is_file()
    assert _dicts(rows[1:]) == [r for name in sorted(files) for r in _read(tmp_path / "both" / ARCHIVE_DIR / name)]


# ----------------------------------------------------------------------------- audit: damaged files, growth


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda b: b"", r"p\.csv\.gz: empty \(0 bytes\)"),
        (lambda b: gzip.compress(b""), r"p\.csv\.gz: empty"),
        (lambda b: b[:30] + bytes([b[30] ^ 0x55]) + b[31:], r"p\.csv\.gz: not a gzipped UTF-8 CSV"),
        (lambda b: gzip.compress(gzip.decompress(b).replace(b"\n", b",x\n", 2)), r"p\.csv\.gz: line 3 does not have"),
        (lambda b: gzip.compress(gzip.decompress(b).replace(b"navigation_time_s", b"nav_time")), r"header .* differs"),
    ],
)
def test_a_damaged_file_is_refused_naming_it(tmp_path: Path, damage, match: str) -> None:
    rows = [["o", "cv", "zara1", "", str(ep), "success", "1.5"] for ep in range(40)]
    rows += [["p", "cv", "zara1", "", str(ep), "success", str(ep / 7)] for ep in range(40)]
    write_archive(tmp_path, archive_files(HEADER, rows), out=lambda s: None)
    path = tmp_path / ARCHIVE_DIR / "p.csv.gz"
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(ValueError, match=match):
        read_rows(tmp_path)


def test_an_older_file_whose_rows_the_new_archive_all_holds_is_removed(tmp_path: Path) -> None:
    old = _table(("planner@none",))
    _legacy(tmp_path, old)
    lines: list[str] = []
    write_archive(tmp_path, archive_files(HEADER, _table()), out=lines.append)  # the grid grew by policies
    assert not (tmp_path / LEGACY_ARCHIVE).exists() and "nothing of it is lost" in lines[-1]
    assert read_rows(tmp_path) == _dicts(_table())


@pytest.mark.parametrize("name", ["", "a/b", "P" * 90])
def test_a_policy_name_no_archive_file_can_hold_is_refused_when_the_config_loads(name: str) -> None:
    from agents.ablation import config_from_mapping
    from crowdnav_mesrnn.config import ConfigError

    with pytest.raises(ConfigError, match="'policies'"):
        config_from_mapping(
            {
                "name": "names",
                "splits": ["zara1"],
                "arms": ["cv"],
                "seeds": [0],
                "policies": {name: {"kind": "planner"}},
                "evaluation": {"episodes": 2, "seed": 0},
            }
        )


def test_an_older_archive_of_a_header_alone_is_not_split(tmp_path: Path) -> None:
    legacy = _legacy(tmp_path, [])
    with pytest.raises(ValueError, match="no episode: nothing to split"):
        split_legacy(tmp_path)
    assert legacy.is_file() and not (tmp_path / ARCHIVE_DIR).exists()  # left whole, nothing written
