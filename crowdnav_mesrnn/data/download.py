"""``crowdnav-mesrnn data download``: fetch the ETH/UCY recordings, verify them, and install them safely.

The project reads a folder holding ``all_data/``, ``train/`` and ``val/`` (SGAN-format text files, metres;
:mod:`crowdnav_mesrnn.data.paths`). This module fills one from either source:

- **The project's own layout** served under a base URL: ``BASE/all_data/biwi_eth.txt``, ``BASE/train/...``,
  ``BASE/val/...`` — one request per file (:data:`ETH_UCY_SHA256` lists them). Any ``http://``, ``https://``
  or ``file://`` base works, and so does a local folder's path.
- **The Social-GAN datasets archive** (:data:`DEFAULT_URL`, a ``.zip``; a local copy's path works too), the copy
  most trajectory-prediction projects use. Its layout differs from ours: it holds one folder per leave-one-out
  split (``datasets/<split>/{train,val,test}/``) and the pieces of every recording under ``datasets/raw/``
  (``raw/all_data/``, ``raw/train/``, ``raw/val/``). Each file we need is taken from ``raw/<part>/<file>``
  when the archive has it there; otherwise a ``_train``/``_val`` piece from any split's ``train/``/``val/``
  folder and a whole recording from any split's ``test/`` folder. Whatever the source, a file is accepted
  only when its SHA-256 equals the pinned one. This path was written from the archive's documented layout
  and tested on archives built locally in that layout; the public URL itself cannot be reached from the
  machines this project is developed on (see the data page of the docs).

What it guarantees:

- **Verified before installed.** Every file is checked against :data:`ETH_UCY_SHA256` (pinned from the
  development copy) in a staging folder beside ``dest``; nothing reaches ``dest`` before all of them verify.
- **Only the project's files.** A new ``dest`` is the staging folder renamed into place (atomic). In an existing
  ``dest`` (``force``) only :data:`OWNED_FILES` are replaced, each by an atomic rename; an error part way puts
  the previous ones back. Nothing else in ``dest`` is touched, and a ``dest`` that is a file is refused.
- **One download per destination.** A lock file beside ``dest`` (``.<name>.lock``, ``fcntl.flock``) is held
  from the check of ``dest`` to the install; a second download into the same folder is refused at once with a
  message naming the running one (it does not wait: when the first ends, running again finds the verified files).
- **Bounded.** Each connection or read may stall ``timeout_s``; the whole transfer ends by ``deadline_s``
  (:class:`~crowdnav_mesrnn.data.deadline.Deadline`), however slowly a server sends; no body or archive member
  is read past its pinned size (:data:`ETH_UCY_BYTES`), and nothing large is held in memory.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import fcntl
import hashlib
import http.client
import os
import shutil
import tempfile
import time
import urllib.error
import urllib.parse
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Final

from crowdnav_mesrnn.data.deadline import SCHEMES, Deadline, finite_seconds
from crowdnav_mesrnn.data.paths import ENV_VAR, DataNotFoundError, candidate_dirs, find_data_dir

#: The Social-GAN datasets archive (a zip; its layout is mapped by :func:`archive_member_for`). Untested here:
#: the machines this project is developed and tested on reach no host but package registries.
DEFAULT_URL: Final[str] = "https://www.dropbox.com/s/8n02xqv3l9q18r1/datasets.zip?dl=1"

#: Where ``data download`` installs by default: the last place the project looks (no configuration needed).
DEFAULT_DEST: Final[Path] = Path.home() / ".cache" / "crowdnav-mesrnn" / "eth_ucy"

#: Seconds a connection or a read may stall before the download fails.
DEFAULT_TIMEOUT_S: Final[float] = 30.0

#: Seconds the whole transfer may take. The Social-GAN archive is tens of MB at most: 30 minutes allow
#: about 20 kB/s for 36 MB, and bound what a server sending a byte per ``timeout`` can hold.
DEFAULT_DEADLINE_S: Final[float] = 1800.0

#: Largest archive accepted, bytes (the Social-GAN archive is a few MB; this bounds a wrong URL's cost).
MAX_ARCHIVE_BYTES: Final[int] = 512 * 1024 * 1024

#: Bytes read at a time from a response or an archive member.
CHUNK_BYTES: Final[int] = 1 << 16

#: ``relative path -> SHA-256`` of every file the project reads, from ``../shared/data/eth_ucy/SHA256SUMS``
#: (``tests/data/test_download.py`` checks this table against that file and the files themselves).
ETH_UCY_SHA256: Final[dict[str, str]] = {
    "all_data/biwi_eth.txt": "cf8d3fd342a15f409ebc2a1fc76b91a0f06390bd21f1e11410f3859331ab082b",
    "all_data/biwi_hotel.txt": "9caa771bb9153d6b809dd0916b6f86761b641e6bbb15e766c1de3133fbbb7fcf",
    "all_data/crowds_zara01.txt": "1147a1962a09abfb86f28c6cddcac862e095a0cf129b3016385b69eacdd09d85",
    "all_data/crowds_zara02.txt": "8a649d0f8c9ae75c87c4d23a85f892786b0aa30266e996c7be03e69dafff22ff",
    "all_data/crowds_zara03.txt": "16b3e899932c4baacd07f45013d5b921f90bc5a29eb2b0fe42f4d7c904ac3108",
    "all_data/students001.txt": "a6d87f278d94136fe39b8be91555487a29ac77259ae403b9dba2d5c18caf7b5b",
    "all_data/students003.txt": "e25798b660634330aa89f8bb259425de720e84d0873902726c1d1f4ccff21d6c",
    "all_data/uni_examples.txt": "61f432c0ab3070ed0ef150fbeabcd7baf839cab5495a46e6105bd747f0a092a7",
    "train/biwi_eth_train.txt": "7905d1337f8466c3ebcd80e8264158209370e939774a371d215491256128407e",
    "train/biwi_hotel_train.txt": "f3f485043273e3d972efd73770df0021ec7d3d5135f60d2e2ca5809f68d6f104",
    "train/crowds_zara01_train.txt": "5b2ff1a334f4b3e8595e0ee898874b1795561db7bde97e90cbc4a1382c8c3d56",
    "train/crowds_zara02_train.txt": "9fd606341135d7d211c3af259c9eb2c25e4c7035efc43d3007ceeef6f954b247",
    "train/crowds_zara03_train.txt": "d38a0a6cd1e24adadbb3b15cac97b747e5c6ace2c59d457d805f38a4d91d5a03",
    "train/students001_train.txt": "f41a0a63301e1c15104205c4a1540db477ddc3330ee2801a976d7b9fc238a63e",
    "train/students003_train.txt": "85fe6324e9a0b94acb21617eb0331f543fe5ebf0caee1e253794bca554f35daf",
    "train/uni_examples_train.txt": "06866bea5c2f589094473371e9fb6b653c7af95e5f748434bc1024544c5e1c7a",
    "val/biwi_eth_val.txt": "ed19f8ee52e024788658d70060c1452b991aa506b78ea649c74f79e075ad20b9",
    "val/biwi_hotel_val.txt": "5c6026c5c6feb81295187e2e063d86197344428811ac2ae98a45bdfb5dfa79ed",
    "val/crowds_zara01_val.txt": "d5212e4e3289aa44365e5ce34a476ef2a4208c89bd6a29204ece097c7f33c157",
    "val/crowds_zara02_val.txt": "361949e5655814680e1185bdd23344932f7b6ccc0d7120c34b523495d0fc69f8",
    "val/crowds_zara03_val.txt": "60d464e21fd3851fab146ec3b35d0db4155b3c057f4b46050336eac59314f0f5",
    "val/students001_val.txt": "dc8f3147820e80642903041b017292eb03ea5df81ffd2974b47a725d8ffeb394",
    "val/students003_val.txt": "b7aa6dcedba0e9036272dc363e2a25e6bb80d7485d75dcb3fff918ce01b10e24",
    "val/uni_examples_val.txt": "436dfa865ffab37957e928e227a1b6cc836ab0e6b7652abbf5d06cdf5638dee4",
}


#: ``relative path -> size in bytes`` of every file the project reads (the files of :data:`ETH_UCY_SHA256`); no
#: response or archive member is read past it (``tests/data/test_download.py`` checks it against the shared copy).
ETH_UCY_BYTES: Final[dict[str, int]] = {
    "all_data/biwi_eth.txt": 116970,
    "all_data/biwi_hotel.txt": 143799,
    "all_data/crowds_zara01.txt": 205711,
    "all_data/crowds_zara02.txt": 392227,
    "all_data/crowds_zara03.txt": 199834,
    "all_data/students001.txt": 879714,
    "all_data/students003.txt": 724279,
    "all_data/uni_examples.txt": 109307,
    "train/biwi_eth_train.txt": 83681,
    "train/biwi_hotel_train.txt": 117490,
    "train/crowds_zara01_train.txt": 171116,
    "train/crowds_zara02_train.txt": 306018,
    "train/crowds_zara03_train.txt": 146945,
    "train/students001_train.txt": 738442,
    "train/students003_train.txt": 629898,
    "train/uni_examples_train.txt": 89740,
    "val/biwi_eth_val.txt": 44273,
    "val/biwi_hotel_val.txt": 39395,
    "val/crowds_zara01_val.txt": 34595,
    "val/crowds_zara02_val.txt": 86209,
    "val/crowds_zara03_val.txt": 52889,
    "val/students001_val.txt": 141272,
    "val/students003_val.txt": 94381,
    "val/uni_examples_val.txt": 19567,
}

#: The files ``data download`` writes into a data folder, and the only ones it ever replaces there.
OWNED_FILES: Final[tuple[str, ...]] = (*ETH_UCY_SHA256, "SHA256SUMS")


class DownloadError(RuntimeError):
    """The data could not be fetched or installed; the message says why and what was left as it was."""


class ChecksumError(DownloadError):
    """A fetched file differs from the pinned one (SHA-256 or size); the message names the file."""


class SourceError(DownloadError):
    """The source could not be read (unreachable, HTTP error, stalled, past the deadline, truncated); the message
    lists the other ways to get the data (:func:`alternatives_hint`)."""


class DestinationError(DownloadError):
    """``dest`` cannot take the data as asked: a file, busy with another download, or holding other data."""


@dataclass(frozen=True)
class DownloadResult:
    """What :func:`download_data` installed."""

    dest: Path
    """The data folder (holds ``all_data/``, ``train/``, ``val/`` and ``SHA256SUMS``)."""
    files: int
    """Files verified against :data:`ETH_UCY_SHA256`."""
    source: str
    """The URL the files came from."""
    already_present: bool
    """``dest`` already held every file, verified; nothing was fetched."""
    found_by_default: bool
    """The project finds ``dest`` without ``--data-dir`` or ``$CROWDNAV_MESRNN_DATA``."""


def is_archive_url(url: str) -> bool:
    """True when ``url`` names a ``.zip`` archive (by its path, ignoring any query string)."""
    return urllib.parse.urlsplit(url).path.lower().endswith(".zip")


_SCHEME_LIST: Final[str] = ", ".join(f"{scheme}://" for scheme in SCHEMES[:-1]) + f" or {SCHEMES[-1]}://"


def source_url(url: str) -> str:
    """``url`` when it is an ``http``, ``https`` or ``file`` URL; a local path (an archive, or a folder in the
    project's layout) as a ``file://`` URL.

    Raises:
        DownloadError: another scheme, or a path that does not exist.
    """
    scheme = urllib.parse.urlsplit(url).scheme.lower()
    if scheme in SCHEMES:
        return url
    if scheme and "://" in url:
        raise DownloadError(f"{url}: unsupported URL scheme {scheme!r}; give an {_SCHEME_LIST} URL or a path")
    path = Path(url).expanduser()
    if not path.exists():
        raise DownloadError(f"{url}: no such file or folder (and not an {_SCHEME_LIST} URL)")
    return path.resolve().as_uri()


def seconds_option(text: str) -> float:
    """``argparse`` type of ``--timeout`` and ``--deadline``: a finite number of seconds > 0."""
    try:
        return finite_seconds("value", text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds > 0, got {text}") from None


def alternatives_hint() -> str:
    """What else works when the download source cannot be read (appended to :class:`SourceError` messages)."""
    places = " and ".join(str(path) for label, path in candidate_dirs(None) if not label.startswith("$"))
    return (
        "Other ways to get the data:\n"
        "  - a mirror or a local copy: --url https://mirror.example/datasets.zip, --url /path/to/datasets.zip or "
        "--url file:///path/to/datasets.zip (the Social-GAN archive), or --url BASE (a URL or folder in the "
        "project's layout);\n"
        f"  - a copy of the folder you already have: `export {ENV_VAR}=/path/to/eth_ucy` (or --data-dir on each "
        "command); no download needed.\n"
        "The folder holds all_data/<recording>.txt, train/<recording>_train.txt and val/<recording>_val.txt "
        "(SGAN format, metres; `crowdnav-mesrnn data check DIR` verifies it). "
        f"Without {ENV_VAR} the project looks in {places}."
    )


def _stream(read: Callable[[int], bytes], sink: BinaryIO, cap: int) -> tuple[int, str]:
    """Copy ``read``'s chunks into ``sink`` until the end or until more than ``cap`` bytes came.

    Returns the bytes read (more than ``cap`` when stopped: at most ``cap`` were written, at most
    ``cap + CHUNK_BYTES`` read) and the SHA-256 of what was written.
    """
    digest, n = hashlib.sha256(), 0
    while chunk := read(CHUNK_BYTES):
        n += len(chunk)
        if n > cap:
            break
        digest.update(chunk)
        sink.write(chunk)
    return n, digest.hexdigest()


def _source_error(url: str, exc: BaseException, timeout_s: float, deadline: Deadline) -> SourceError:
    if deadline.expired:
        what = (
            f"not finished within the deadline of {deadline.seconds:g} s (--deadline; the server sends too "
            "slowly or stalls)"
        )
    elif isinstance(exc, urllib.error.HTTPError):
        what = f"HTTP {exc.code} {exc.reason}"
    elif isinstance(exc, http.client.IncompleteRead):
        what = f"truncated download ({len(exc.partial)} bytes, then the connection closed)"
    elif isinstance(exc, TimeoutError) or isinstance(getattr(exc, "reason", None), TimeoutError):
        what = f"no answer within {timeout_s:g} s (timed out; --timeout)"
    elif isinstance(exc, urllib.error.URLError):
        what = f"unreachable ({exc.reason})"
    else:
        what = f"download failed ({type(exc).__name__}: {exc})"
    return _source_failure(url, what)


def _source_failure(url: str, what: str) -> SourceError:
    return SourceError(f"{url}: {what}. Nothing was installed.\n{alternatives_hint()}")


@contextlib.contextmanager
def _reading(url: str, timeout_s: float, deadline: Deadline) -> Iterator[None]:
    """Turns the errors of reading ``url`` into a :class:`SourceError` saying which."""
    try:
        yield
    except (OSError, http.client.HTTPException) as exc:
        raise _source_error(url, exc, timeout_s, deadline) from exc


def _fetch(url: str, out: Path, deadline: Deadline, timeout_s: float, limit: int, limit_note: str) -> tuple[int, str]:
    """Stream the body of ``url`` into the file ``out``; its size in bytes and SHA-256.

    Raises :class:`SourceError` on an unreachable host, a stall longer than ``timeout_s``, the deadline, an HTTP
    error or a body shorter than its ``Content-Length``; :class:`DownloadError` on a body longer than ``limit``
    bytes (``limit_note`` says what that limit is), refused before more than ``limit + CHUNK_BYTES`` are read.
    """

    def too_long(size: str) -> DownloadError:
        return DownloadError(f"{url}: {size} bytes, more than {limit_note} ({limit} bytes); is this the right URL?")

    with open(out, "wb") as sink:
        with _reading(url, timeout_s, deadline):
            resp = deadline.urlopen(url, timeout_s)
        with resp:
            expected = resp.headers.get("Content-Length")
            if expected is not None and expected.isdigit() and int(expected) > limit:
                raise too_long(expected)

            def read(size: int) -> bytes:
                with _reading(url, timeout_s, deadline):
                    chunk = resp.read(size)
                    deadline.check()
                return chunk

            got, digest = _stream(read, sink, limit)
    if got > limit:
        raise too_long(f"more than {limit}")
    if expected is not None and expected.isdigit() and got != int(expected):
        raise _source_failure(url, f"truncated download ({got} of {expected} bytes)")
    return got, digest


def _check_digest(rel: str, digest: str, size: int, source: str) -> None:
    want = ETH_UCY_SHA256[rel]
    if digest != want:
        raise ChecksumError(
            f"{rel}: SHA-256 {digest} does not match the pinned {want} (from {source}, {size} bytes). "
            "The file is corrupt, truncated or a different version of the recording; nothing was installed."
        )


def archive_member_for(rel: str, members: list[str]) -> list[str]:
    """Members of a Social-GAN-layout archive that may hold our file ``rel`` (``part/file``), best first.

    ``raw/<part>/<file>`` first; then a ``_train``/``_val`` piece from any split's ``train/``/``val/`` folder,
    or a whole recording (``all_data``) from any split's ``test/`` folder. Matching is on path components, so
    the archive's top folder (``datasets/``) may have any name.
    """
    part, name = rel.split("/")
    raw, other = [], []
    for m in members:
        parts = m.strip("/").split("/")
        if len(parts) < 2 or parts[-1] != name:
            continue
        if len(parts) >= 3 and parts[-3] == "raw" and parts[-2] == part:
            raw.append(m)
        elif parts[-2] == ("test" if part == "all_data" else part):
            other.append(m)
    return sorted(raw) + sorted(other)


def _extract(zf: zipfile.ZipFile, member: str, rel: str, out: Path, source: str) -> None:
    """Stream ``member`` into ``out``, refusing it as soon as it grows past ``rel``'s pinned size, and verify it."""
    cap = ETH_UCY_BYTES[rel]
    with open(out, "wb") as sink:
        try:
            with zf.open(member) as src:
                size, digest = _stream(src.read, sink, cap)
        except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError, OSError) as exc:
            raise DownloadError(f"{rel}: {source} unreadable ({type(exc).__name__}: {exc})") from exc
    if size > cap:
        raise ChecksumError(
            f"{rel}: {source} is larger than the pinned {cap} bytes (refused after reading {size} bytes); "
            "nothing was installed."
        )
    _check_digest(rel, digest, size, source)


def _from_archive(url: str, staging: Path, payload: Path, deadline: Deadline, timeout_s: float) -> None:
    archive = staging / "archive.zip"
    _fetch(url, archive, deadline, timeout_s, MAX_ARCHIVE_BYTES, "the largest archive accepted")
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        size = archive.stat().st_size
        raise DownloadError(f"{url}: not a readable zip archive ({size} bytes; truncated download?)") from exc
    with zf:
        members = [i.filename for i in zf.infolist() if not i.is_dir()]
        for rel in ETH_UCY_SHA256:
            candidates = archive_member_for(rel, members)
            if not candidates:
                raise DownloadError(
                    f"{rel}: not in the archive {url} (looked for raw/{rel} and the leave-one-out split folders)"
                )
            (payload / rel).parent.mkdir(parents=True, exist_ok=True)
            mismatch: ChecksumError | None = None
            for member in candidates:
                try:
                    _extract(zf, member, rel, payload / rel, f"{url} member {member}")
                    break
                except ChecksumError as exc:
                    mismatch = mismatch or exc
            else:
                assert mismatch is not None
                raise mismatch
    archive.unlink()


def _from_layout(
    base: str, payload: Path, deadline: Deadline, timeout_s: float, progress: Callable[[str], None]
) -> None:
    base = base.rstrip("/")
    for k, rel in enumerate(ETH_UCY_SHA256, start=1):
        url = f"{base}/{rel}"
        (payload / rel).parent.mkdir(parents=True, exist_ok=True)
        size, digest = _fetch(url, payload / rel, deadline, timeout_s, ETH_UCY_BYTES[rel], f"the pinned size of {rel}")
        _check_digest(rel, digest, size, url)
        progress(f"  [{k}/{len(ETH_UCY_SHA256)}] {rel}")


def _data_in_use() -> tuple[str, Path] | None:
    """The data folder the project would use with no argument, with where it was found; None if none."""
    try:
        path = find_data_dir()
    except DataNotFoundError:
        return None
    return next((label, p) for label, p in candidate_dirs(None) if p == path)


def verify_folder(root: Path) -> list[str]:
    """Problems of ``root`` against :data:`ETH_UCY_SHA256` (missing or differing files); empty when it matches."""
    problems = []
    for rel, want in ETH_UCY_SHA256.items():
        path = root / rel
        if not path.is_file():
            problems.append(f"{path}: missing")
        elif _sha256_file(path) != want:
            problems.append(f"{path}: SHA-256 differs from the pinned one")
    return problems


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


def found_by_default(dest: Path) -> bool:
    """True when the project finds ``dest`` with no argument (``$CROWDNAV_MESRNN_DATA`` set to it, or the first
    of ``./data/eth_ucy`` / the user cache holding data)."""
    dest = dest.resolve()
    for label, path in candidate_dirs(None):
        path = path.resolve()
        if path == dest:
            return True
        if label.startswith("$") or (path / "all_data").is_dir():
            return False  # the variable, or an earlier folder holding data, wins
    return False


def where_hint(dest: Path, default: bool) -> str:
    """How the project will find ``dest`` (printed after a download)."""
    if default:
        env = os.environ.get(ENV_VAR)
        if env and Path(env).expanduser().resolve() == dest.resolve():
            return f"The project finds it there through ${ENV_VAR}."
        return (
            f"The project finds it there with no configuration (searched: {ENV_VAR}, ./data/eth_ucy, the user cache)."
        )
    return (
        f"The project does not look there by default: `export {ENV_VAR}={dest}` (or pass `--data-dir {dest}` to "
        "each command)."
    )


def lock_path(dest: Path) -> Path:
    """The lock file of downloads into ``dest``: ``.<name>.lock`` beside the real folder (symbolic links
    resolved, so every spelling of one folder shares one lock). Present only while a download runs."""
    real = dest.expanduser().resolve()
    return real.parent / f".{real.name}.lock"


@contextlib.contextmanager
def _install_lock(dest: Path) -> Iterator[None]:
    """Hold :func:`lock_path` for the block, or raise :class:`DestinationError` at once when another download
    holds it. The file is removed on exit; a lock taken on a file its holder removed meanwhile is retaken."""
    lock = lock_path(dest)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DestinationError(f"{dest}: cannot create the lock file {lock} ({exc}); nothing was changed") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise DestinationError(
                f"{dest}: another `crowdnav-mesrnn data download` is installing there (pid {holder}; lock {lock}). "
                "Nothing was changed; when it has finished, run the command again (it will find the verified files)."
            ) from None
        except BaseException:
            os.close(fd)
            raise
        try:
            current = os.stat(lock)
        except FileNotFoundError:
            current = None
        if current is not None and os.path.samestat(os.fstat(fd), current):
            break
        os.close(fd)  # the previous holder removed this file as we opened it: take the new one
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # before unlocking, so no one can lock the removed file unnoticed
        os.close(fd)


def _check_destination(dest: Path, force: bool) -> bool:
    """True when ``dest`` already holds every file, verified. Raises :class:`DestinationError` when ``dest`` is
    not a folder, when one of :data:`OWNED_FILES` (or its folder) is in the way as the wrong kind of entry, or
    when ``dest`` holds anything but the verified files and ``force`` is False."""
    if dest.is_symlink() and not dest.exists():
        raise DestinationError(f"--dest {dest} is a broken symbolic link; nothing was changed")
    if dest.exists() and not dest.is_dir():
        raise DestinationError(
            f"--dest {dest} is a file, not a folder; nothing was changed. The data goes into a folder: choose a "
            "folder path (it is created when missing)."
        )
    if not dest.exists():
        return False
    problems = verify_folder(dest)
    if not problems:
        return True
    for rel in OWNED_FILES:
        path = dest / rel
        if path.parent.exists() and not path.parent.is_dir():
            raise DestinationError(f"{path.parent} is a file where the data needs a folder; nothing was changed")
        if path.is_dir():
            raise DestinationError(f"{path} is a folder where the data needs a file; nothing was changed")
    if not force and any(dest.iterdir()):
        raise DestinationError(
            f"{dest} exists and does not hold the verified ETH/UCY files ({len(problems)} of "
            f"{len(ETH_UCY_SHA256)} missing or different, e.g. {problems[0]}); choose another --dest, or pass "
            f"--force to replace the project's files in it (the {len(ETH_UCY_SHA256)} pinned recordings and "
            "SHA256SUMS; nothing else in the folder is touched)"
        )
    return False


def _move_in(payload: Path, dest: Path, backup: Path) -> None:
    """Move :data:`OWNED_FILES` from ``payload`` into the existing folder ``dest``, each by an atomic rename. The
    files they replace are kept in ``backup`` (same file system) until all are in; an error part way puts them
    back and removes what was added, and is raised."""
    done: list[tuple[str, bool]] = []  # (file, it replaced one)
    made: list[Path] = []
    try:
        for rel in OWNED_FILES:
            target = dest / rel
            if not target.parent.is_dir():
                target.parent.mkdir()
                made.append(target.parent)
            replaces = target.exists() or target.is_symlink()
            if replaces:
                (backup / rel).parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.link(target, backup / rel, follow_symlinks=False)  # target never goes missing
                except OSError:
                    shutil.copy2(target, backup / rel, follow_symlinks=False)
            os.replace(payload / rel, target)
            done.append((rel, replaces))
    except BaseException:
        for rel, replaced in reversed(done):
            with contextlib.suppress(OSError):
                if replaced:
                    os.replace(backup / rel, dest / rel)
                else:
                    (dest / rel).unlink()
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def _install(staging: Path, payload: Path, dest: Path) -> None:
    """Put the verified ``payload`` at ``dest``: renamed into place when ``dest`` does not exist, else its files
    moved in (:func:`_move_in`)."""
    if not (dest.exists() or dest.is_symlink()):
        try:
            os.rename(payload, dest)
            return
        except OSError as exc:
            if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY):
                raise
            raise DestinationError(f"{dest} appeared during the download; nothing was changed, run again") from exc
    _move_in(payload, dest, staging / "previous")


def _fetch_and_install(
    url: str, staging: Path, dest: Path, timeout_s: float, deadline_s: float, progress: Callable[[str], None]
) -> None:
    """Fetch every file into ``staging/new`` (an archive into ``staging`` first), verify it there, install it."""
    payload = staging / "new"  # made by mkdir, so a folder renamed into place gets the user's usual permissions
    payload.mkdir()
    with Deadline(deadline_s) as deadline:
        if is_archive_url(url):
            _from_archive(url, staging, payload, deadline, timeout_s)
        else:
            _from_layout(url, payload, deadline, timeout_s, progress)
    sums = "".join(f"{ETH_UCY_SHA256[rel]}  {rel}\n" for rel in sorted(ETH_UCY_SHA256))
    (payload / "SHA256SUMS").write_text(sums)
    problems = verify_folder(payload)  # what is on disk, not what was streamed
    if problems:
        raise DownloadError("written files do not verify: " + "; ".join(problems))
    _install(staging, payload, dest)


def download_data(
    dest: str | os.PathLike[str] | None = None,
    url: str | None = None,
    *,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    deadline_s: float = DEFAULT_DEADLINE_S,
    force: bool = False,
    progress: Callable[[str], None] = lambda _msg: None,
) -> DownloadResult:
    """Fetch, verify and install the ETH/UCY recordings in the project's layout.

    Args:
        dest: the data folder to create or fill; a file is refused. When None: if the project already uses a
            folder other than :data:`DEFAULT_DEST` (``$CROWDNAV_MESRNN_DATA`` or ``./data/eth_ucy``, the first
            holding data), that folder is returned when it verifies (nothing fetched) and refused when not (a copy
            in the user cache would not be used); otherwise :data:`DEFAULT_DEST`, the user cache.
        url: a ``.zip`` in the Social-GAN layout (default :data:`DEFAULT_URL`), or a base URL serving the
            project's layout (``BASE/all_data/biwi_eth.txt``, ``BASE/train/...``, ``BASE/val/...``); ``http``,
            ``https`` or ``file`` URLs, or a local path to either.
        timeout_s: seconds a connection or a read may stall before failing (finite, > 0).
        deadline_s: seconds the whole transfer may take (finite, > 0), however slowly the server sends.
        force: in an existing ``dest`` that does not verify, replace the project's files (:data:`OWNED_FILES`);
            nothing else in it is touched. A verified ``dest`` is kept either way; an empty one is filled.
        progress: called with one line of text per step.

    Returns:
        What was installed where (:class:`DownloadResult`).

    Raises:
        ValueError: ``timeout_s`` or ``deadline_s`` is not a finite number of seconds > 0.
        SourceError: unreachable URL, time-out, deadline, HTTP error or truncated body; the message lists the
            other ways to get the data.
        ChecksumError: a file differs from its pinned SHA-256 or size (the message names it).
        DestinationError: ``dest`` is a file, another download into it is running, or it holds other files and
            ``force`` is False; or ``dest`` is None and the folder the project uses does not verify.
        DownloadError: any other failure (a file missing from the source, an unreadable archive, a write error).
            After any error ``dest`` holds what it held before.
    """
    timeout_s = finite_seconds("timeout_s", timeout_s)
    deadline_s = finite_seconds("deadline_s", deadline_s)
    url = source_url(url or DEFAULT_URL)
    if dest is None:  # no folder asked for: the one the project already uses may hold the data
        in_use = _data_in_use()
        if in_use is not None and in_use[1].resolve() != DEFAULT_DEST.resolve():
            label, path = in_use
            problems = verify_folder(path)
            if problems:  # a copy in the user cache would not be used while this folder holds all_data/
                raise DestinationError(
                    f"the project uses {path} ({label}), which does not verify: {problems[0]}"
                    + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")
                    + f"; a download into {DEFAULT_DEST} would not be used while it holds all_data/. Nothing was "
                    f"fetched. Repair it with `crowdnav-mesrnn data download --dest {path} --force` (replaces only "
                    "the project's files), or download elsewhere with --dest and point the project there"
                )
            progress(
                f"the project already uses {path} ({label}), which holds every file, verified: nothing to fetch "
                "(the pinned files are the same from any --url; pass --dest to download a copy elsewhere)"
            )
            return DownloadResult(path, len(ETH_UCY_SHA256), str(path), True, found_by_default(path))
    dest = Path(dest).expanduser() if dest is not None else DEFAULT_DEST
    home = lock_path(dest).parent  # the lock and the staging folder live beside the real folder
    try:
        home.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DestinationError(f"{dest}: cannot create the folder {home} ({exc})") from exc
    with _install_lock(dest):
        try:
            if _check_destination(dest, force):
                return DownloadResult(dest, len(ETH_UCY_SHA256), str(dest), True, found_by_default(dest))
            started = time.perf_counter()
            progress(f"fetching {url}")
            staging = Path(tempfile.mkdtemp(prefix=f".{dest.name}.download-", dir=home))
            try:
                _fetch_and_install(url, staging, dest, timeout_s, deadline_s, progress)
            finally:
                shutil.rmtree(staging, ignore_errors=True)
        except OSError as exc:
            raise DownloadError(f"{dest}: {exc}; it holds what it held before") from exc
    progress(f"verified {len(ETH_UCY_SHA256)} files in {time.perf_counter() - started:.1f} s")
    return DownloadResult(dest, len(ETH_UCY_SHA256), url, False, found_by_default(dest))
