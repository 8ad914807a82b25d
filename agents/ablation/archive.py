"""The episode archive of a grid's committed results on disk: one gzipped CSV per policy.

``python -m agents.ablation.split_archive FOLDER [FOLDER ...]`` moves a results folder's older single
``episodes.csv.gz`` into this layout row for row (:func:`split_legacy`), without re-rendering anything.

Layout
    ``<out_dir>/episodes/<file name>.csv.gz`` (:data:`ARCHIVE_DIR`) holds every evaluated episode of one policy (all
    its arms, splits and training seeds), sorted by arm, split, training seed and episode. Every file of a grid has the
    same header (:data:`agents.ablation.episodes.ARCHIVE_KEYS`, the metrics, the counts), the ``policy`` column
    included. The grid's archive is these files read in the order of their policies' names (Python string order), and
    that is row for row what the single ``episodes.csv.gz`` (:data:`LEGACY_ARCHIVE`) held before. One file per policy
    keeps each file a few MiB: the reactive grid's 90,000 episodes took 10.5 MiB in one file.

File names
    :func:`archive_name` keeps the policy's name where it is ASCII lower-case letters, digits, ``_``, ``-``, ``@`` and
    ``.`` (not as the first character) and writes every other character as ``%XX``, one per UTF-8 byte, with upper-case
    hex digits (percent-encoding, as in URLs). A name that Windows reserves (``con``, ``prn``, ``aux``, ``nul``,
    ``com1``-``com9``, ``lpt1``-``lpt9``) also gets its first letter escaped. Then ``.csv.gz`` is appended:
    ``planner@orca`` -> ``planner@orca.csv.gz``, ``PPO`` -> ``%50%50%4F.csv.gz``, ``a/b`` -> ``a%2Fb.csv.gz``.
    :func:`archive_policy` decodes the name (URL unquoting). Every policy has exactly one file name, and two policies
    never share one, even on a file system that ignores case. A ``.csv.gz`` file there whose name is not the encoding
    of some policy is refused, and so is a file holding another policy's rows.

Rules
    - Reading a folder (:func:`read_rows`) takes ``episodes/``, else the older ``episodes.csv.gz``. When both are there,
      they must hold the same rows: the same columns in the same order, the same values and the same row order.
      Otherwise :class:`ArchiveConflict` names both.
    - Writing (:func:`write_archive`) writes each file atomically. A folder without ``episodes/`` gets the whole folder
      at once: it is written beside under a temporary name, then renamed.
    - Nothing is deleted that the writer did not create. The older ``episodes.csv.gz`` is removed only when the new
      files, read back from disk, hold every one of its rows with every value (exactly its rows, or more: a grid that
      grew); removing it then loses nothing. Otherwise it is left, with a warning, and readers refuse the folder until
      one of the two is removed.
    - Every file is read whole and checked: a file that is empty, not gzip, or has a row with more or fewer fields than
      its header, or a header other than the other files', is an error naming it (and the line). A file in ``episodes/``
      that this write did not produce is left too, with a warning (a policy no longer in the grid).
"""

from __future__ import annotations

import csv
import gzip
import io
import os
import shutil
import string
import tempfile
import urllib.parse
import zlib
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Final

from crowdnav_mesrnn.utils import atomic_write

#: The folder of a results folder (``out_dir``) that holds the episode archive, one file per policy.
ARCHIVE_DIR: Final[str] = "episodes"
#: The single archive file that results folders held before (read still; :func:`split_legacy` moves it).
LEGACY_ARCHIVE: Final[str] = "episodes.csv.gz"
#: The ending of every archive file's name.
SUFFIX: Final[str] = ".csv.gz"
#: The column naming the policy: the key by which the archive is split into files.
POLICY_COLUMN: Final[str] = "policy"

_KEPT: Final[frozenset[str]] = frozenset(string.ascii_lowercase + string.digits + "_-@.")
_WINDOWS_RESERVED: Final[frozenset[str]] = frozenset(
    {"con", "prn", "aux", "nul", *(f"com{i}" for i in range(1, 10)), *(f"lpt{i}" for i in range(1, 10))}
)

Rows = list[dict[str, str]]


class ArchiveConflict(ValueError):
    """A results folder holds both ``episodes/`` and the older ``episodes.csv.gz``, with different rows. The message
    names both and the first difference."""


def _escape(ch: str) -> str:
    return "".join(f"%{b:02X}" for b in ch.encode("utf-8"))


def archive_name(policy: str) -> str:
    """The file name (in ``episodes/``) of ``policy``'s episodes: see the module's *File names*."""
    if not policy:
        raise ValueError("an archive file needs a policy name; got ''")
    stem = "".join(ch if ch in _KEPT and not (i == 0 and ch == ".") else _escape(ch) for i, ch in enumerate(policy))
    if stem.split(".", 1)[0] in _WINDOWS_RESERVED:
        stem = _escape(stem[0]) + stem[1:]
    return stem + SUFFIX


def archive_policy(name: str) -> str:
    """The policy whose episodes the archive file ``name`` holds; the inverse of :func:`archive_name`. Raises
    :class:`ValueError` when ``name`` is not the file name of any policy."""
    stem = name.removesuffix(SUFFIX)
    try:
        policy = urllib.parse.unquote(stem, errors="strict") if stem and stem != name else ""
    except UnicodeDecodeError:
        policy = ""
    if not policy or archive_name(policy) != name:
        expected = f" (that policy's file is {archive_name(policy)!r})" if policy else ""
        raise ValueError(
            f"{name!r} is not the archive file name of a policy{expected}: the names are the policies' names, "
            "percent-encoded, with .csv.gz (agents.ablation.archive)"
        )
    return policy


def _gzip_csv(header: Sequence[str], rows: Iterable[Sequence[object]]) -> bytes:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return gzip.compress(buf.getvalue().encode("utf-8"), mtime=0)


def archive_files(header: Sequence[str], rows: Iterable[Sequence[object]]) -> dict[str, bytes]:
    """A table split into the archive's files: ``{file name: gzipped CSV}``, one file per value of the ``policy``
    column. Each file holds ``header`` and that policy's rows in their order. The files come in the order of their
    policies' names and are byte-identical for identical input."""
    column = list(header).index(POLICY_COLUMN)
    groups: dict[str, list[Sequence[object]]] = {}
    for row in rows:
        groups.setdefault(str(row[column]), []).append(row)
    return {archive_name(policy): _gzip_csv(header, groups[policy]) for policy in sorted(groups)}


def _text(data: bytes, where: str | os.PathLike[str]) -> str:
    """The text of a gzipped UTF-8 file; :class:`ValueError` naming ``where`` when it is not one (or is empty)."""
    try:
        text = gzip.decompress(data).decode("utf-8")
    except (OSError, EOFError, UnicodeDecodeError, zlib.error) as exc:
        raise ValueError(f"{where}: not a gzipped UTF-8 CSV ({exc})") from None
    if not text.strip():
        raise ValueError(f"{where}: empty{' (0 bytes)' if not data else ''}: not a gzipped CSV with a header line")
    return text


def _table(data: bytes, where: str | os.PathLike[str]) -> Rows:
    """The rows of a gzipped CSV (one dict per row, in the header's column order). Raises :class:`ValueError` naming
    the file, and the line for a row with more or fewer fields than the header."""
    return _header_rows(data, where)[1]


def read_file(path: str | os.PathLike[str]) -> Rows:
    """The rows of one gzipped CSV of an archive (or any gzipped episode CSV), checked as :func:`_table` checks them:
    a damaged, empty or ragged file is a :class:`ValueError` naming it."""
    return _table(Path(path).read_bytes(), path)


def _header_rows(data: bytes, where: str | os.PathLike[str]) -> tuple[list[str], Rows]:
    reader = csv.DictReader(io.StringIO(_text(data, where)))
    rows: Rows = []
    try:
        for row in reader:
            if None in row or None in row.values():
                raise ValueError(
                    f"{where}: line {reader.line_num} does not have the header's {len(reader.fieldnames or ())} fields"
                )
            rows.append(row)
    except csv.Error as exc:
        raise ValueError(f"{where}: line {reader.line_num}: {exc}") from None
    return list(reader.fieldnames or ()), rows


def files_rows(files: Mapping[str, bytes], where: str | os.PathLike[str] = ARCHIVE_DIR) -> Rows:
    """The rows of archive files (``{file name: gzipped CSV}``), in the order of their policies' names. Raises
    :class:`ValueError` naming the file (in folder ``where``) for a name that is no policy's, or a row of another
    policy."""
    rows: Rows = []
    first: tuple[str, list[str]] | None = None
    for policy, name in sorted((archive_policy(name), name) for name in files):
        header, table = _header_rows(files[name], f"{where}/{name}")
        if first is None:
            first = (name, header)
        elif header != first[1]:
            raise ValueError(
                f"{where}/{name}: its header {header} differs from that of {where}/{first[0]} {first[1]}; every file "
                "of an archive has the same columns"
            )
        for i, row in enumerate(table, start=1):
            if row.get(POLICY_COLUMN) != policy:
                raise ValueError(
                    f"{where}/{name}: row {i} is of policy {row.get(POLICY_COLUMN)!r}; the file holds {policy!r}'s "
                    "episodes only"
                )
        rows += table
    return rows


def has_archive(folder: str | os.PathLike[str]) -> bool:
    """``folder`` holds an episode archive: ``episodes/``, or the older ``episodes.csv.gz``."""
    return (Path(folder) / ARCHIVE_DIR).is_dir() or (Path(folder) / LEGACY_ARCHIVE).is_file()


def archive_path(folder: str | os.PathLike[str]) -> Path:
    """Where ``folder``'s archive is, to name it in messages: ``episodes/``, unless only the older file is there."""
    folder = Path(folder)
    if not (folder / ARCHIVE_DIR).is_dir() and (folder / LEGACY_ARCHIVE).is_file():
        return folder / LEGACY_ARCHIVE
    return folder / ARCHIVE_DIR


def read_files(folder: str | os.PathLike[str]) -> dict[str, bytes]:
    """The ``*.csv.gz`` files in ``folder``'s ``episodes/`` by name (empty when there is none)."""
    target = Path(folder) / ARCHIVE_DIR
    if not target.is_dir():
        return {}
    return {p.name: p.read_bytes() for p in sorted(target.iterdir()) if p.name.endswith(SUFFIX) and p.is_file()}


def same_rows(a: Rows, b: Rows) -> bool:
    """Exactly the same rows: the same columns in the same order, the same values, the same row order."""
    return len(a) == len(b) and all(list(x.items()) == list(y.items()) for x, y in zip(a, b, strict=True))


def _first_difference(a: Rows, b: Rows) -> str:
    for i, (x, y) in enumerate(zip(a, b, strict=False), start=1):
        if list(x.items()) != list(y.items()):
            what = ", ".join(f"{k} {x.get(k)}" for k in ("policy", "arm", "split", "seed", "episode"))
            return f"row {i} differs ({what})"
    return f"{len(a)} rows against {len(b)}"


def read_rows(folder: str | os.PathLike[str]) -> Rows:
    """Every archived episode of a results folder (:mod:`agents.ablation.archive`'s *Rules*): ``episodes/``'s rows,
    else the older ``episodes.csv.gz``'s; empty when there is neither. Raises :class:`ArchiveConflict` when both are
    there with different rows, and :class:`ValueError` for a file that is not an archive's."""
    folder = Path(folder)
    legacy = folder / LEGACY_ARCHIVE
    new = files_rows(read_files(folder), folder / ARCHIVE_DIR) if (folder / ARCHIVE_DIR).is_dir() else None
    old = _table(legacy.read_bytes(), legacy) if legacy.is_file() else None
    if new is not None and old is not None and not same_rows(new, old):
        raise ArchiveConflict(
            f"{folder} holds two episode archives that differ: {folder / ARCHIVE_DIR}/ ({len(new)} rows) and the older "
            f"{legacy} ({len(old)} rows); {_first_difference(new, old)}. "
            + (
                f"Every row of {legacy} is in {ARCHIVE_DIR}/: remove {legacy}."
                if _holds(new, old)
                else f"Remove the one that does not belong with {folder / 'cells.json'}. A summary of other episodes "
                "leaves the older file, with a warning."
            )
        )
    return new if new is not None else old or []


def stored_as(folder: str | os.PathLike[str], files: Mapping[str, bytes], rows: Rows | None = None) -> str:
    """How ``folder``'s archive stands against ``files`` (with their rows ``rows``, read here if ``None``):
    ``"same"`` when ``episodes/`` holds exactly these files, byte for byte, and there is no older file; ``"rows"``
    when it holds the same rows (:func:`same_rows`) in another layout or in other bytes; ``""`` otherwise."""
    folder = Path(folder)
    target = folder / ARCHIVE_DIR
    if target.is_dir() and not (folder / LEGACY_ARCHIVE).exists():
        names = {p.name for p in target.iterdir() if p.name.endswith(SUFFIX)}
        if names == set(files) and all((target / n).read_bytes() == data for n, data in files.items()):
            return "same"
    if not has_archive(folder):
        return ""
    return "rows" if same_rows(read_rows(folder), files_rows(files) if rows is None else rows) else ""


def write_archive(
    folder: str | os.PathLike[str], files: Mapping[str, bytes], out: Callable[[str], None] = print
) -> None:
    """Write ``files`` (:func:`archive_files`) into ``folder``'s ``episodes/`` (the module's *Rules*). Each file is
    written atomically, and only where its bytes differ; a folder without ``episodes/`` gets it whole. Then: files
    there that ``files`` does not name are left, with a warning; the older ``episodes.csv.gz`` is removed when its rows
    are all in the files (:func:`settle_legacy`)."""
    folder = Path(folder)
    target = folder / ARCHIVE_DIR
    if not target.exists():
        folder.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{ARCHIVE_DIR}-", dir=folder))
        try:
            for name, data in files.items():
                atomic_write(staging / name, lambda fh, data=data: fh.write(data))
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(staging, 0o777 & ~umask)  # mkdtemp creates 0700; give the folder the usual permissions
            os.rename(staging, target)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    else:
        for name, data in files.items():
            if not ((target / name).is_file() and (target / name).read_bytes() == data):
                atomic_write(target / name, lambda fh, data=data: fh.write(data))
    others = sorted(p.name for p in target.iterdir() if p.name.endswith(SUFFIX) and p.name not in files)
    if others:
        out(
            f"warning: left {len(others)} file(s) in {target}/ that this archive does not hold (policies without "
            f"episodes here): {', '.join(others)}. Remove them if an earlier summary of this grid wrote them; until "
            "then no summary of these results counts as unchanged."
        )
    settle_legacy(folder, files_rows({n: (target / n).read_bytes() for n in files}, target), out)


def settle_legacy(folder: str | os.PathLike[str], rows: Rows, out: Callable[[str], None] = print) -> bool:
    """Remove ``folder``'s older ``episodes.csv.gz`` when its rows are exactly ``rows`` (the rows of the new files on
    disk: it is then the grid's own earlier archive), or every one of them is among ``rows`` with every value (a grid
    that grew: removing it loses nothing), and say so. Otherwise leave it and say why in a warning.
    Returns whether it was removed (``False`` also when there is none)."""
    legacy = Path(folder) / LEGACY_ARCHIVE
    if not legacy.is_file():
        return False
    old = _table(legacy.read_bytes(), legacy)
    target = Path(folder) / ARCHIVE_DIR
    if same_rows(old, rows):
        legacy.unlink()
        out(f"removed {legacy}: its {len(old)} rows are exactly those of {target}/, which now holds them per policy")
        return True
    if _holds(rows, old):
        legacy.unlink()
        out(
            f"removed {legacy}: each of its {len(old)} rows is in {target}/ ({len(rows)} rows), every value as there; "
            "nothing of it is lost"
        )
        return True
    out(
        f"warning: left {legacy} as it is: its rows differ from those of {target}/ ({_first_difference(old, rows)}), "
        f"so it is not this archive's earlier form. Readers refuse {folder} while it holds both; remove the older file "
        "once you no longer need it."
    )
    return False


def _holds(new: Rows, old: Rows) -> bool:
    """Every row of ``old`` is a distinct row of ``new``, with the same value in each of ``old``'s columns (``new`` may
    have more rows, and more columns): removing ``old`` loses nothing."""
    if not old:
        return True
    columns = list(old[0])
    if not new or not set(columns) <= set(new[0]):
        return False
    need = Counter(tuple(r.get(c) for c in columns) for r in old)
    have = Counter(tuple(r.get(c) for c in columns) for r in new)
    return all(have[k] >= n for k, n in need.items())


def split_legacy(folder: str | os.PathLike[str], out: Callable[[str], None] = print) -> dict[str, bytes]:
    """Move ``folder``'s older single ``episodes.csv.gz`` into ``episodes/``, row for row and without re-rendering
    anything. The header and every value stay as they are (an archive too old for a re-render keeps its columns and
    rounding). The older file is removed once the new files read back its rows exactly. Returns the files.

    Raises :class:`FileNotFoundError` when there is no older file. Raises :class:`ValueError` when it holds no row
    (the files would not keep its header) or its rows are not in the order of their policies' names (splitting would
    reorder them), and :class:`ArchiveConflict` when
    ``episodes/`` is there already with other rows. Nothing is written in these cases."""
    folder = Path(folder)
    legacy = folder / LEGACY_ARCHIVE
    if not legacy.is_file():
        raise FileNotFoundError(f"{legacy} does not exist: nothing to split")
    data = legacy.read_bytes()
    header, *rows = list(csv.reader(io.StringIO(_text(data, legacy))))
    if POLICY_COLUMN not in header:
        raise ValueError(f"{legacy}: no {POLICY_COLUMN!r} column in its header {header}")
    if not rows:
        raise ValueError(
            f"{legacy}: a header and no episode: nothing to split (its columns would be lost); left as it is"
        )
    files = archive_files(header, rows)
    old = _table(data, legacy)
    if not same_rows(files_rows(files), old):
        raise ValueError(
            f"{legacy}: its rows are not in the order of their policies' names, so the files of {ARCHIVE_DIR}/ would "
            "list them in another order; left as it is"
        )
    if (folder / ARCHIVE_DIR).exists():
        read_rows(folder)  # raises ArchiveConflict unless episodes/ holds these rows already
        settle_legacy(folder, files_rows(read_files(folder), folder / ARCHIVE_DIR), out)
        return read_files(folder)
    write_archive(folder, files, out)
    return files
