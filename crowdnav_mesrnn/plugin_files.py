"""What identifies a plug-in's code and data on disk: a digest of the files of its distribution.

The forecast cache keys a plug-in's forecasts on its identity (:meth:`crowdnav_mesrnn.predictors.PredictorSpec.identity`);
:func:`files_digest` is the part of it that changes when any file of the plug-in changes — another module, a parameter
file, shipped weights — not only the module holding its factory:

- **An installed distribution** (``pip install .``): the files its ``RECORD`` lists, each by the SHA-256 pip wrote there
  when installing it. A file changed since (its size differs from the record, or it was modified after ``RECORD`` was
  written) enters by the hash of what is on disk now.
- **An editable install, a source tree or a bare import path** (``RECORD`` missing, or listing none of the package's
  files): every file of the target's top-level package folder (or its single module file), by content.

Left out, as they say nothing about the forecasts and differ between machines holding the same plug-in: the
distribution's metadata folder (``*.dist-info``, ``*.egg-info``; the version is part of the identity anyway), byte
code (``__pycache__``, ``.pyc``), ``.pth`` files and editable-install finders, and files outside ``site-packages``
(console scripts, whose first line names the interpreter). Paths enter relative to ``site-packages`` (or to the
package folder's parent), so the same plug-in installed on two machines has one digest (the Ray backend compares them).
Content hashes are remembered per process by (path, size, modification time).
"""

from __future__ import annotations

import base64
import hashlib
import importlib.metadata
import importlib.util
import os
from pathlib import Path
from typing import Any

#: Content digests already computed: absolute path -> ((size, mtime_ns), digest).
_HASHED: dict[str, tuple[tuple[int, int], str]] = {}


def files_digest(module: str, distribution: str | None) -> str:
    """SHA-256 over ``(relative path, file digest)`` of every file that makes up the plug-in whose factory lives in
    ``module``, installed by ``distribution`` (None: a bare import path); see the module docstring for which files.
    Empty string when neither the distribution nor the module can be found."""
    rows = _record_rows(distribution, module)
    if rows is None:
        rows = _folder_rows(module)
    if not rows:
        return ""
    h = hashlib.sha256()
    for rel, digest in sorted(rows):
        h.update(f"{rel}\0{digest}\n".encode())
    return h.hexdigest()


def _skipped(rel: str) -> bool:
    """Files that do not describe the plug-in's forecasts, or differ per machine (see the module docstring)."""
    parts = Path(rel).parts
    return (
        not parts
        or parts[0] == ".."
        or any(p == "__pycache__" or p.endswith((".dist-info", ".egg-info")) for p in parts)
        or rel.endswith((".pyc", ".pth"))
        or parts[-1].startswith("__editable__")
    )


def _distribution(name: str | None) -> Any:
    if not name:
        return None
    try:
        return importlib.metadata.distribution(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def _record_rows(distribution: str | None, module: str) -> list[tuple[str, str]] | None:
    """``(path, digest)`` of the files ``RECORD`` lists, or None when there is no ``RECORD`` or it lists no file of
    ``module``'s top-level package (an editable install)."""
    dist = _distribution(distribution)
    files = dist.files if dist is not None else None
    if not files:
        return None
    record = next((f for f in files if f.name == "RECORD" and str(f.parent).endswith(".dist-info")), None)
    record_path = Path(str(record.locate())) if record is not None else None
    if record_path is None or not record_path.is_file():
        return None
    recorded_at = record_path.stat().st_mtime_ns
    top = module.partition(".")[0]
    rows: list[tuple[str, str]] = []
    covers_module = False
    for f in files:
        rel = str(f).replace(os.sep, "/")
        if _skipped(rel):
            continue
        covers_module = covers_module or Path(rel).parts[0] in (top, f"{top}.py")
        path = Path(str(f.locate()))
        rows.append((rel, _recorded_or_current(path, f.hash, f.size, recorded_at)))
    return rows if covers_module else None


def _recorded_or_current(path: Path, recorded: Any, size: int | None, recorded_at: int) -> str:
    """The file's SHA-256 as ``RECORD`` has it while the file is as installed; else the hash of its content now."""
    try:
        st = path.stat()
    except OSError:
        return "missing"
    untouched = recorded is not None and recorded.mode == "sha256" and size == st.st_size
    if untouched and st.st_mtime_ns < recorded_at:  # written before RECORD: as pip installed it
        return recorded.value
    return _content_hash(path, st)


def _folder_rows(module: str) -> list[tuple[str, str]]:
    """``(path, digest)`` of every file of ``module``'s top-level package folder (or its module file), by content."""
    top = module.partition(".")[0]
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return []
    if spec is None:
        return []
    folders = list(spec.submodule_search_locations or [])
    if not folders:  # a single module file
        if not spec.origin or not os.path.isfile(spec.origin):
            return []
        path = Path(spec.origin)
        return [(path.name, _content_hash(path, path.stat()))]
    rows = []
    for folder in map(Path, folders):
        for root, dirs, names in os.walk(folder):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__" and not d.startswith("."))
            for name in names:
                path = Path(root, name)
                rel = path.relative_to(folder.parent).as_posix()
                if not _skipped(rel) and path.is_file():
                    rows.append((rel, _content_hash(path, path.stat())))
    return rows


def _content_hash(path: Path, st: os.stat_result) -> str:
    """The file's SHA-256 written as ``RECORD`` writes it (URL-safe base64 without padding), so a file hashed here and
    the same file as recorded give one value; remembered by (path, size, modification time)."""
    key = str(path.resolve())
    stamp = (st.st_size, st.st_mtime_ns)
    held = _HASHED.get(key)
    if held is not None and held[0] == stamp:
        return held[1]
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    digest = base64.urlsafe_b64encode(h.digest()).rstrip(b"=").decode()
    _HASHED[key] = (stamp, digest)
    return digest
