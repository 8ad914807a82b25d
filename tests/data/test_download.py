"""``crowdnav-mesrnn data download`` end to end against a loopback HTTP server serving the shared files.

Every server binds 127.0.0.1 on a random port, runs in a daemon thread, answers a bounded number of
requests and is shut down by its fixture.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import http.server
import shutil
import socket
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data.download import (
    ETH_UCY_SHA256,
    ChecksumError,
    DownloadError,
    archive_member_for,
    download_data,
    found_by_default,
)
from crowdnav_mesrnn.data.paths import ENV_VAR, HOW_TO_GET_DATA

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
def serve(root: Path) -> Iterator[str]:
    """``http://127.0.0.1:PORT`` serving ``root`` until the block ends."""
    handler = functools.partial(_Handler, directory=str(root))
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


def test_existing_unverified_dest_needs_force(served_copy: Path, tmp_path: Path) -> None:
    dest = tmp_path / "eth_ucy"
    dest.mkdir()
    (dest / "note.txt").write_text("mine")
    with pytest.raises(DownloadError, match="--force"):
        download_data(dest, "http://127.0.0.1:9/", timeout_s=1)
    assert (dest / "note.txt").read_text() == "mine"
    with serve(served_copy) as base:
        download_data(dest, base, timeout_s=10, force=True)
    assert not (dest / "note.txt").exists() and (dest / "all_data" / "biwi_eth.txt").is_file()


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
