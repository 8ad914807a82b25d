"""``crowdnav-mesrnn data download``: fetch the ETH/UCY recordings, verify them, and install them atomically.

The project reads a folder holding ``all_data/``, ``train/`` and ``val/`` (SGAN-format text files, metres;
:mod:`crowdnav_mesrnn.data.paths`). This module fills one from either source:

- **The project's own layout** served under a base URL: ``BASE/all_data/biwi_eth.txt``, ``BASE/train/...``,
  ``BASE/val/...`` — one request per file (:data:`ETH_UCY_SHA256` lists them). Any ``http://``, ``https://``
  or ``file://`` base works.
- **The Social-GAN datasets archive** (:data:`DEFAULT_URL`, a ``.zip``), the copy most trajectory-prediction
  projects use. Its layout differs from ours: it holds one folder per leave-one-out split
  (``datasets/<split>/{train,val,test}/``) and the pieces of every recording under ``datasets/raw/``
  (``raw/all_data/``, ``raw/train/``, ``raw/val/``). Each file we need is taken from ``raw/<part>/<file>``
  when the archive has it there; otherwise a ``_train``/``_val`` piece from any split's ``train/``/``val/``
  folder and a whole recording from any split's ``test/`` folder. Whatever the source, a file is accepted
  only when its SHA-256 equals the pinned one. This path was written from the archive's documented layout
  and tested on archives built locally in that layout; the public URL itself cannot be reached from the
  machines this project is developed on (see the data page of the docs).

Every file is verified against :data:`ETH_UCY_SHA256` (pinned from the development copy) before anything
is installed. Files are downloaded into a temporary folder beside ``dest`` and the folder is renamed onto
``dest`` only when all of them are verified, so ``dest`` is never half-written: after an error it is
either absent or the folder that was there before.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import shutil
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from crowdnav_mesrnn.data.paths import ENV_VAR, candidate_dirs

#: The Social-GAN datasets archive (a zip; its layout is mapped by :func:`archive_member_for`). Untested here:
#: the machines this project is developed and tested on reach no host but package registries.
DEFAULT_URL: Final[str] = "https://www.dropbox.com/s/8n02xqv3l9q18r1/datasets.zip?dl=1"

#: Where ``data download`` installs by default: the last place the project looks (no configuration needed).
DEFAULT_DEST: Final[Path] = Path.home() / ".cache" / "crowdnav-mesrnn" / "eth_ucy"

#: Seconds a connection or a read may stall before the download fails.
DEFAULT_TIMEOUT_S: Final[float] = 30.0

#: Largest archive accepted, bytes (the Social-GAN archive is a few MB; this bounds a wrong URL's cost).
MAX_ARCHIVE_BYTES: Final[int] = 512 * 1024 * 1024

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


class DownloadError(RuntimeError):
    """The data could not be fetched (unreachable, timed out, truncated, missing from the source)."""


class ChecksumError(DownloadError):
    """A fetched file's SHA-256 differs from the pinned one; the message names the file."""


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


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _fetch(url: str, timeout_s: float, limit: int) -> bytes:
    """The body of ``url``; raises :class:`DownloadError` on an unreachable host, a stall longer than
    ``timeout_s``, an HTTP error, a body shorter than its ``Content-Length`` or longer than ``limit`` bytes."""
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp:
            expected = resp.headers.get("Content-Length")
            chunks, got = [], 0
            while True:
                chunk = resp.read(1 << 16)
                if not chunk:
                    break
                got += len(chunk)
                if got > limit:
                    raise DownloadError(f"{url}: more than {limit} bytes; is this the right URL?")
                chunks.append(chunk)
    except urllib.error.HTTPError as exc:
        raise DownloadError(f"{url}: HTTP {exc.code} {exc.reason}") from exc
    except http.client.IncompleteRead as exc:
        raise DownloadError(
            f"{url}: truncated download ({len(exc.partial)} bytes, then the connection closed)"
        ) from exc
    except TimeoutError as exc:
        raise DownloadError(f"{url}: no answer within {timeout_s:g} s (timed out)") from exc
    except urllib.error.URLError as exc:
        raise DownloadError(f"{url}: unreachable ({exc.reason})") from exc
    except (OSError, http.client.HTTPException) as exc:
        raise DownloadError(f"{url}: download failed ({type(exc).__name__}: {exc})") from exc
    if expected is not None and expected.isdigit() and got != int(expected):
        raise DownloadError(f"{url}: truncated download ({got} of {expected} bytes)")
    return b"".join(chunks)


def _verified(rel: str, data: bytes, source: str) -> bytes:
    want = ETH_UCY_SHA256[rel]
    got = _sha256(data)
    if got != want:
        raise ChecksumError(
            f"{rel}: SHA-256 {got} does not match the pinned {want} (from {source}, {len(data)} bytes). "
            "The file is corrupt, truncated or a different version of the recording; nothing was installed."
        )
    return data


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


def _from_archive(url: str, timeout_s: float) -> dict[str, bytes]:
    blob = _fetch(url, timeout_s, MAX_ARCHIVE_BYTES)
    try:
        import io

        zf = zipfile.ZipFile(io.BytesIO(blob))
    except zipfile.BadZipFile as exc:
        raise DownloadError(f"{url}: not a readable zip archive ({len(blob)} bytes; truncated download?)") from exc
    out: dict[str, bytes] = {}
    with zf:
        members = [i.filename for i in zf.infolist() if not i.is_dir()]
        for rel in ETH_UCY_SHA256:
            candidates = archive_member_for(rel, members)
            if not candidates:
                raise DownloadError(
                    f"{rel}: not in the archive {url} (looked for raw/{rel} and the leave-one-out split folders)"
                )
            mismatch: ChecksumError | None = None
            for member in candidates:
                try:
                    data = zf.read(member)
                except (zipfile.BadZipFile, OSError) as exc:
                    raise DownloadError(f"{rel}: archive member {member} unreadable ({exc})") from exc
                try:
                    out[rel] = _verified(rel, data, f"{url} member {member}")
                    break
                except ChecksumError as exc:
                    mismatch = mismatch or exc
            else:
                assert mismatch is not None
                raise mismatch
    return out


def _from_layout(base: str, timeout_s: float, progress: Callable[[str], None]) -> dict[str, bytes]:
    base = base.rstrip("/")
    out: dict[str, bytes] = {}
    for k, rel in enumerate(ETH_UCY_SHA256, start=1):
        url = f"{base}/{rel}"
        out[rel] = _verified(rel, _fetch(url, timeout_s, MAX_ARCHIVE_BYTES), url)
        progress(f"  [{k}/{len(ETH_UCY_SHA256)}] {rel}")
    return out


def verify_folder(root: Path) -> list[str]:
    """Problems of ``root`` against :data:`ETH_UCY_SHA256` (missing or differing files); empty when it matches."""
    problems = []
    for rel, want in ETH_UCY_SHA256.items():
        path = root / rel
        if not path.is_file():
            problems.append(f"{path}: missing")
        elif _sha256(path.read_bytes()) != want:
            problems.append(f"{path}: SHA-256 differs from the pinned one")
    return problems


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
        return (
            f"The project finds it there with no configuration (searched: {ENV_VAR}, ./data/eth_ucy, the user cache)."
        )
    return (
        f"The project does not look there by default: `export {ENV_VAR}={dest}` (or pass `--data-dir {dest}` to "
        "each command)."
    )


def download_data(
    dest: str | os.PathLike[str] | None = None,
    url: str | None = None,
    *,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    force: bool = False,
    progress: Callable[[str], None] = lambda _msg: None,
) -> DownloadResult:
    """Fetch, verify and install the ETH/UCY recordings in the project's layout.

    Args:
        dest: the data folder to create (default :data:`DEFAULT_DEST`, the user cache the project searches).
        url: a ``.zip`` in the Social-GAN layout (default :data:`DEFAULT_URL`), or a base URL serving the
            project's layout (``BASE/all_data/biwi_eth.txt``, ``BASE/train/...``, ``BASE/val/...``).
        timeout_s: seconds a connection or a read may stall before failing.
        force: replace an existing ``dest`` that does not verify (a verified one is kept either way).
        progress: called with one line of text per step.

    Returns:
        What was installed where (:class:`DownloadResult`).

    Raises:
        DownloadError: unreachable URL, time-out, HTTP error, truncated body, a file missing from the source,
            or ``dest`` exists, does not verify and ``force`` is False.
        ChecksumError: a file differs from its pinned SHA-256 (the message names it). ``dest`` is untouched.
    """
    dest = Path(dest).expanduser() if dest is not None else DEFAULT_DEST
    url = url or DEFAULT_URL
    if not (timeout_s > 0):
        raise ValueError(f"timeout_s must be > 0 seconds, got {timeout_s!r}")
    if dest.exists():
        if dest.is_dir() and not verify_folder(dest):
            return DownloadResult(dest, len(ETH_UCY_SHA256), str(dest), True, found_by_default(dest))
        if not force:
            raise DownloadError(
                f"{dest} exists and does not hold the verified ETH/UCY files; choose another --dest, or pass "
                "--force to replace it"
            )
    started = time.perf_counter()
    progress(f"fetching {url}")
    files = _from_archive(url, timeout_s) if is_archive_url(url) else _from_layout(url, timeout_s, progress)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.download-", dir=dest.parent))
    old: Path | None = None
    try:
        for rel, data in files.items():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp / rel).write_bytes(data)
        sums = "".join(f"{ETH_UCY_SHA256[rel]}  {rel}\n" for rel in sorted(files))
        (tmp / "SHA256SUMS").write_text(sums)
        problems = verify_folder(tmp)  # what is on disk, not what was in memory
        if problems:
            raise DownloadError("written files do not verify: " + "; ".join(problems))
        if dest.exists():  # force: move the old folder aside, swap, then delete it
            old = Path(tempfile.mkdtemp(prefix=f".{dest.name}.old-", dir=dest.parent))
            os.replace(dest, old / dest.name)
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not dest.exists() and (old / dest.name).exists():
            os.replace(old / dest.name, dest)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    progress(f"verified {len(files)} files in {time.perf_counter() - started:.1f} s")
    return DownloadResult(dest, len(files), url, False, found_by_default(dest))
