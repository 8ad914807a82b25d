"""``crowdnav-mesrnn data download`` end to end against a loopback HTTP server serving the shared files.

Every server binds 127.0.0.1 on a random port, runs in a daemon thread, answers a bounded number of
requests and is shut down by its fixture.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import hashlib
import http.server
import math
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

import crowdnav_mesrnn.data.download as download
from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data.download import (
    CHUNK_BYTES,
    ETH_UCY_BYTES,
    ETH_UCY_SHA256,
    ChecksumError,
    DestinationError,
    DownloadError,
    SourceError,
    archive_member_for,
    download_data,
    found_by_default,
    lock_path,
    verify_folder,
)
from crowdnav_mesrnn.data.paths import ENV_VAR, HOW_TO_GET_DATA

ROOT = Path(__file__).resolve().parents[2]
TRUNCATE: set[str] = set()


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves a folder; paths in ``TRUNCATE`` announce their full length and send half of it."""

    def log_message(self, *args: object) -> None:  # keep test output clean
        pass

    def do_GET(self) -> None:
        rel = self.path.lstrip("/")
        if rel in TRUNCATE:
            body = (Path(self.directory) / rel).read_bytes()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            return
        super().do_GET()


@contextlib.contextmanager
def serve(root: Path, handler_class: type[http.server.BaseHTTPRequestHandler] = _Handler) -> Iterator[str]:
    """``http://127.0.0.1:PORT`` serving ``root`` (with ``handler_class``) until the block ends."""
    handler = functools.partial(handler_class, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.timeout = 5
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)
        TRUNCATE.clear()


@pytest.fixture
def served_copy(data_dir: Path, tmp_path: Path) -> Path:
    """A copy of the shared data (the project's layout) that a test may corrupt."""
    root = tmp_path / "served"
    for rel in ETH_UCY_SHA256:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(data_dir / rel, root / rel)
    return root


def test_pinned_sums_match_the_shared_copy(data_dir: Path) -> None:
    listed = {}
    for line in (data_dir / "SHA256SUMS").read_text().splitlines():
        if line.strip():
            digest, rel = line.split()
            listed[rel] = digest
    assert listed == ETH_UCY_SHA256
    for rel, digest in ETH_UCY_SHA256.items():
        assert hashlib.sha256((data_dir / rel).read_bytes()).hexdigest() == digest, rel
    assert {rel: (data_dir / rel).stat().st_size for rel in ETH_UCY_SHA256} == ETH_UCY_BYTES


def test_download_then_check_passes(served_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dest = tmp_path / "out" / "eth_ucy"
    with serve(served_copy) as base:
        assert main(["data", "download", "--url", base, "--dest", str(dest), "--timeout", "10"]) == 0
    out = capsys.readouterr().out
    assert str(dest) in out and "24 files" in out and ENV_VAR in out  # not a default place: says how to use it
    assert sorted(p.name for p in dest.iterdir()) == ["SHA256SUMS", "all_data", "train", "val"]
    assert main(["data", "check", str(dest)]) == 0
    assert "checksums verified against SHA256SUMS: OK" in capsys.readouterr().out
    assert [p.name for p in dest.parent.iterdir()] == ["eth_ucy"]  # no temporary folder left behind
    # a second run finds the verified folder and fetches nothing (the server is gone)
    assert download_data(dest, "http://127.0.0.1:9/", timeout_s=1).already_present


def test_corrupted_file_fails_naming_it_and_installs_nothing(served_copy: Path, tmp_path: Path) -> None:
    target = served_copy / "train" / "students003_train.txt"
    target.write_bytes(target.read_bytes().replace(b"1", b"7", 1))
    dest = tmp_path / "eth_ucy"
    with serve(served_copy) as base, pytest.raises(ChecksumError, match=r"train/students003_train\.txt: SHA-256"):
        download_data(dest, base, timeout_s=10)
    assert not dest.exists()
    assert list(tmp_path.glob(".eth_ucy*")) == []
    with serve(served_copy) as base:
        assert main(["data", "download", "--url", base, "--dest", str(dest)]) == 1


def test_truncated_download_is_an_error(served_copy: Path, tmp_path: Path) -> None:
    TRUNCATE.add("val/biwi_hotel_val.txt")
    with serve(served_copy) as base, pytest.raises(DownloadError, match=r"biwi_hotel_val\.txt: truncated download"):
        download_data(tmp_path / "eth_ucy", base, timeout_s=10)
    assert not (tmp_path / "eth_ucy").exists()


def test_unreachable_url_fails_fast(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.perf_counter()
    assert main(["data", "download", "--url", f"http://127.0.0.1:{port}", "--dest", str(tmp_path / "d")]) == 1
    err = capsys.readouterr().err
    assert "unreachable" in err and f"127.0.0.1:{port}/all_data/biwi_eth.txt" in err
    assert time.perf_counter() - started < 30  # bounded, far below a default TCP time-out
    # ... and says what else works: a mirror or local copy, the variable, the layout, the places searched
    for alternative in ("--url https://", "--url /path/to/datasets.zip", "--url file:///", f"export {ENV_VAR}="):
        assert alternative in err
    assert "all_data/<recording>.txt, train/<recording>_train.txt and val/<recording>_val.txt" in err
    assert str(Path.cwd() / "data" / "eth_ucy") in err and str(Path.home() / ".cache/crowdnav-mesrnn/eth_ucy") in err


def test_silent_server_times_out(tmp_path: Path) -> None:
    with socket.socket() as listener:  # accepts connections (backlog) but never answers
        listener.bind(("127.0.0.1", 0))
        listener.listen(4)
        port = listener.getsockname()[1]
        with pytest.raises(DownloadError, match=r"no answer within 0\.5 s"):
            download_data(tmp_path / "d", f"http://127.0.0.1:{port}", timeout_s=0.5)
    assert not (tmp_path / "d").exists()


def _sgan_archive(data_dir: Path, path: Path, with_raw_pieces: bool) -> Path:
    """A zip in the Social-GAN layout: ``datasets/raw/all_data`` (+ ``raw/train``, ``raw/val`` if asked) and the
    five leave-one-out split folders (``datasets/<split>/{train,val,test}``)."""
    from crowdnav_mesrnn.data.constants import SPLIT_TEST_RECORDINGS

    with zipfile.ZipFile(path, "w") as zf:
        for rel in ETH_UCY_SHA256:
            part = rel.split("/")[0]
            if part == "all_data" or with_raw_pieces:
                zf.write(data_dir / rel, f"datasets/raw/{rel}")
        for split, tests in SPLIT_TEST_RECORDINGS.items():
            for rec in tests:
                zf.write(data_dir / "all_data" / f"{rec}.txt", f"datasets/{split}/test/{rec}.txt")
            for part in ("train", "val"):
                for f in sorted((data_dir / part).glob("*.txt")):
                    if f.name.rsplit("_", 1)[0] not in tests:
                        zf.write(f, f"datasets/{split}/{part}/{f.name}")
    return path


@pytest.mark.parametrize("with_raw_pieces", [True, False])
def test_social_gan_archive_layout_is_mapped(data_dir: Path, tmp_path: Path, with_raw_pieces: bool) -> None:
    site = tmp_path / "site"
    site.mkdir()
    _sgan_archive(data_dir, site / "datasets.zip", with_raw_pieces)
    dest = tmp_path / "eth_ucy"
    with serve(site) as base:
        result = download_data(dest, f"{base}/datasets.zip?dl=1", timeout_s=10)
    assert result.files == 24 and not result.already_present
    assert main(["data", "check", str(dest)]) == 0


def test_truncated_archive_is_an_error(data_dir: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    site.mkdir()
    blob = _sgan_archive(data_dir, tmp_path / "full.zip", True).read_bytes()
    (site / "datasets.zip").write_bytes(blob[: len(blob) // 3])  # served whole: a short file, not a short read
    with serve(site) as base, pytest.raises(DownloadError, match="not a readable zip archive"):
        download_data(tmp_path / "eth_ucy", f"{base}/datasets.zip", timeout_s=10)


def test_archive_member_mapping_prefers_raw() -> None:
    members = [
        "datasets/zara1/train/biwi_eth_train.txt",
        "datasets/raw/train/biwi_eth_train.txt",
        "datasets/eth/test/biwi_eth.txt",
        "datasets/raw/all_data/biwi_eth.txt",
    ]
    assert archive_member_for("train/biwi_eth_train.txt", members) == members[1::-1]
    assert archive_member_for("all_data/biwi_eth.txt", members) == [members[3], members[2]]
    assert archive_member_for("val/biwi_eth_val.txt", members) == []


def _snapshot(root: Path) -> dict[str, bytes | None]:
    """Every entry under ``root``: a file's bytes, ``None`` for a folder."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def _user_folder(dest: Path) -> None:
    """A data folder a user also keeps other things in, with one of the project's files edited."""
    (dest / "runs" / "r1").mkdir(parents=True)
    (dest / "runs" / "r1" / "log.txt").write_text("a run")
    (dest / "note.txt").write_text("mine")
    (dest / "all_data").mkdir()
    (dest / "all_data" / "my_scene.txt").write_text("my own recording")
    (dest / "all_data" / "biwi_eth.txt").write_text("edited")


def test_force_replaces_only_the_projects_files(served_copy: Path, tmp_path: Path) -> None:
    dest = tmp_path / "eth_ucy"
    _user_folder(dest)
    before = _snapshot(dest)
    with pytest.raises(DownloadError, match="--force"):
        download_data(dest, "http://127.0.0.1:9/", timeout_s=1)
    assert _snapshot(dest) == before
    with serve(served_copy) as base:
        download_data(dest, base, timeout_s=10, force=True)
    assert verify_folder(dest) == [] and (dest / "SHA256SUMS").is_file()
    after = _snapshot(dest)
    for rel in ("runs", "runs/r1", "runs/r1/log.txt", "note.txt", "all_data/my_scene.txt"):
        assert after[rel] == before[rel], rel  # the user's files and folders are all there, unchanged
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eth_ucy", "served"]  # no staging folder, no lock


def test_an_empty_dest_is_filled_without_force(served_copy: Path, tmp_path: Path) -> None:
    dest = tmp_path / "eth_ucy"
    dest.mkdir()
    with serve(served_copy) as base:
        assert not download_data(dest, base, timeout_s=10).already_present
    assert verify_folder(dest) == []


def test_dest_that_is_a_file_is_refused_even_with_force(
    served_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dest = tmp_path / "thesis.tex"
    dest.write_text("months of work")
    with serve(served_copy) as base:
        assert main(["data", "download", "--url", base, "--dest", str(dest), "--force"]) == 1
    assert f"--dest {dest} is a file, not a folder" in capsys.readouterr().err
    assert dest.read_text() == "months of work"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["served", "thesis.tex"]


def test_an_install_error_puts_the_previous_files_back(
    served_copy: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dest = tmp_path / "eth_ucy"
    _user_folder(dest)
    before = _snapshot(dest)
    real_replace, moved = os.replace, []

    def replace_failing_at_the_fifth(src: object, dst: object) -> None:
        moved.append(dst)
        if len(moved) == 5:
            raise OSError(errno.ENOSPC, "No space left on device (simulated)")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace_failing_at_the_fifth)
    with serve(served_copy) as base, pytest.raises(DownloadError, match=r"No space left .*holds what it held before"):
        download_data(dest, base, timeout_s=10, force=True)
    monkeypatch.undo()
    assert len(moved) > 5  # four files were in: they were put back
    assert _snapshot(dest) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eth_ucy", "served"]


def test_a_second_download_into_one_destination_is_refused(served_copy: Path, tmp_path: Path) -> None:
    """A download in another process holds the destination (its first request is held by the server): a second
    one is refused at once, naming it, and changes nothing; the first then installs."""
    arrived, release, taken = threading.Event(), threading.Event(), threading.Lock()

    class HoldFirst(_Handler):
        def do_GET(self) -> None:
            if taken.acquire(blocking=False):  # the first request only
                arrived.set()
                release.wait(60)
            super().do_GET()

    dest = tmp_path / "eth_ucy"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    with serve(served_copy, HoldFirst) as base:
        first = subprocess.Popen(
            [sys.executable, "-m", "crowdnav_mesrnn.cli", "data", "download", "--url", base, "--dest", str(dest)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert arrived.wait(60), "the first download never reached the server"
            assert lock_path(dest).is_file()
            started = time.perf_counter()
            with pytest.raises(
                DestinationError, match=rf"another .*data download.* is installing there \(pid {first.pid};"
            ):
                download_data(dest, base, timeout_s=10)
            assert time.perf_counter() - started < 5  # refused at once, not after a download
            assert not dest.exists()
        finally:
            release.set()
            out, err = first.communicate(timeout=120)
    assert first.returncode == 0, err
    assert "24 files" in out and verify_folder(dest) == []
    assert not lock_path(dest).exists()


class _Trickle(_Handler):
    """Sends a 100 kB file one byte every 0.1 s — the status line and headers too when ``slow_headers`` — for at
    most 10 s (so the test ends even against a client without a deadline)."""

    slow_headers = False

    def do_GET(self) -> None:
        head = b"HTTP/1.1 200 OK\r\nContent-Length: 100000\r\n\r\n"
        if not self.slow_headers:
            self.wfile.write(head)
            head = b""
        body = head + b"1" * 100_000
        stop = time.monotonic() + 10
        for k in range(len(body)):
            if time.monotonic() > stop:
                return
            try:
                self.wfile.write(body[k : k + 1])
                self.wfile.flush()
            except OSError:
                return  # the client went away
            time.sleep(0.1)


@pytest.mark.parametrize("slow_headers", [False, True], ids=["body", "headers"])
def test_a_trickling_server_hits_the_deadline(tmp_path: Path, slow_headers: bool) -> None:
    handler = type("Trickle", (_Trickle,), {"slow_headers": slow_headers})
    started = time.perf_counter()
    with serve(tmp_path, handler) as base, pytest.raises(SourceError, match=r"deadline of 1\.5 s") as exc:
        download_data(tmp_path / "eth_ucy", base, timeout_s=1, deadline_s=1.5)
    assert time.perf_counter() - started < 1.5 + 3  # each byte came within --timeout: only the deadline ends it
    assert "all_data/biwi_eth.txt" in str(exc.value) and "--url" in str(exc.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("flag", ["--timeout", "--deadline"])
@pytest.mark.parametrize("value", ["inf", "nan", "0", "-1", "soon"])
def test_seconds_must_be_finite_and_positive(
    flag: str, value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["data", "download", "--url", "http://127.0.0.1:9/", "--dest", str(tmp_path / "d"), flag, value])
    assert exc.value.code == 2
    assert f"argument {flag}: must be a finite number of seconds > 0, got {value}" in capsys.readouterr().err
    for name in ("timeout_s", "deadline_s"):
        for bad in (math.inf, math.nan, 0.0):
            with pytest.raises(ValueError, match=rf"{name} must be a finite number of seconds > 0, got {bad!r}"):
                download_data(tmp_path / "d", "http://127.0.0.1:9/", **{name: bad})
    assert not (tmp_path / "d").exists()


def test_an_oversized_archive_member_is_refused_while_streaming(
    data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``biwi_eth.txt`` followed by 32 MiB (compressed to a few dozen kB): refused once past its pinned size,
    having decompressed at most one chunk more."""
    archive = tmp_path / "datasets.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for rel in ETH_UCY_SHA256:
            with zf.open(f"datasets/raw/{rel}", "w", force_zip64=True) as member:
                member.write((data_dir / rel).read_bytes())
                if rel == "all_data/biwi_eth.txt":
                    for _ in range(32):
                        member.write(b"0" * (1 << 20))
    assert archive.stat().st_size < 8 << 20
    decompressed: list[int] = []
    real_read = zipfile.ZipExtFile.read

    def counting_read(self: zipfile.ZipExtFile, n: int | None = -1) -> bytes:
        data = real_read(self, n)
        decompressed.append(len(data))
        return data

    monkeypatch.setattr(zipfile.ZipExtFile, "read", counting_read)
    pinned = ETH_UCY_BYTES["all_data/biwi_eth.txt"]
    with pytest.raises(ChecksumError, match=rf"all_data/biwi_eth\.txt: .* is larger than the pinned {pinned} bytes"):
        download_data(tmp_path / "eth_ucy", archive.as_uri(), timeout_s=10)
    assert sum(decompressed) <= pinned + CHUNK_BYTES
    assert not (tmp_path / "eth_ucy").exists()


def test_a_local_archive_or_folder_is_a_source(
    data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    archive = _sgan_archive(data_dir, tmp_path / "datasets.zip", with_raw_pieces=False)
    for k, url in enumerate([str(archive), archive.as_uri(), str(data_dir)]):
        dest = tmp_path / f"d{k}"
        assert main(["data", "download", "--url", url, "--dest", str(dest)]) == 0, capsys.readouterr().err
        assert verify_folder(dest) == []
    assert main(["data", "download", "--url", str(tmp_path / "missing.zip"), "--dest", str(tmp_path / "e")]) == 1
    assert "missing.zip: no such file or folder" in capsys.readouterr().err


def test_default_place_is_found(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert found_by_default(tmp_path / "data" / "eth_ucy")
    assert not found_by_default(tmp_path / "elsewhere")
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "elsewhere"))
    assert found_by_default(tmp_path / "elsewhere")


def test_no_data_message_names_the_command() -> None:
    assert "crowdnav-mesrnn data download" in HOW_TO_GET_DATA


@pytest.mark.parametrize("where", ["variable", "working directory"])
def test_without_dest_a_folder_in_use_is_checked_kept_when_it_verifies_and_refused_when_not(
    served_copy: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    where: str,
) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    cache = tmp_path / "home" / ".cache" / "crowdnav-mesrnn" / "eth_ucy"
    monkeypatch.setattr(download, "DEFAULT_DEST", cache)
    if where == "variable":
        monkeypatch.chdir(tmp_path)
        monkeypatch.setenv(ENV_VAR, str(served_copy))
        label = f"${ENV_VAR}"
    else:  # ./data/eth_ucy, found before the user cache
        monkeypatch.delenv(ENV_VAR, raising=False)
        (tmp_path / "work" / "data").mkdir(parents=True)
        served_copy = served_copy.rename(tmp_path / "work" / "data" / "eth_ucy")
        monkeypatch.chdir(tmp_path / "work")
        label = "working directory"
    # the source is unreachable: a download would fail
    assert main(["data", "download", "--url", "http://127.0.0.1:9/", "--timeout", "1"]) == 0
    out = capsys.readouterr().out
    assert f"the project already uses {served_copy} ({label})" in out and "24 files" in out
    hint = f"finds it there through ${ENV_VAR}" if where == "variable" else "finds it there with no configuration"
    assert hint in out
    assert not (tmp_path / "home").exists()  # nothing written into the default place
    # a folder in use that does not verify is named with its file, and nothing is fetched or written
    target = served_copy / "val" / "biwi_hotel_val.txt"
    target.write_bytes(target.read_bytes()[:-10])
    before = _snapshot(served_copy)
    assert main(["data", "download", "--url", "http://127.0.0.1:9/", "--timeout", "1"]) == 1
    err = capsys.readouterr().err
    assert f"the project uses {served_copy} ({label}), which does not verify" in err
    assert "biwi_hotel_val.txt" in err and f"--dest {served_copy} --force" in err and "unreachable" not in err
    assert _snapshot(served_copy) == before and not (tmp_path / "home").exists()


def test_the_named_repair_restores_a_folder_in_use(
    data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "mine"
    for rel in ETH_UCY_SHA256:
        (broken / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(data_dir / rel, broken / rel)
    (broken / "val" / "biwi_hotel_val.txt").write_text("damaged\n")
    monkeypatch.setenv(ENV_VAR, str(broken))
    monkeypatch.setattr(download, "DEFAULT_DEST", tmp_path / "cache")
    assert main(["data", "download", "--url", str(data_dir)]) == 1
    assert main(["data", "download", "--url", str(data_dir), "--dest", str(broken), "--force"]) == 0
    assert verify_folder(broken) == []
    capsys.readouterr()
    assert main(["data", "download", "--url", "http://127.0.0.1:9/"]) == 0
    assert "already uses" in capsys.readouterr().out
