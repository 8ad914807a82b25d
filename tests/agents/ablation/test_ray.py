"""agents.ablation on Ray, the connection: an address where nothing listens is refused before any cell starts,
a failed ``ray.init`` is one clear message, and a token in ``~/.ray/auth_token`` turns token authentication on
as ``ray start`` does (issue 16, items 4 and 5). The grid on a real head and a killed task: test_ablation_e2e.py."""

from __future__ import annotations

import io
import json
import socket
import tarfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import agents.ablation as ab
import agents.ablation.ray_backend as rb
from crowdnav_mesrnn.config import ConfigError


def _grid(tmp_path: Path) -> ab.AblationConfig:
    return ab.config_from_mapping(
        {
            "name": "ray",
            "runs_dir": str(tmp_path / "runs"),
            "out_dir": str(tmp_path / "results"),
            "splits": ["zara1"],
            "arms": ["none"],
            "seeds": [0],
            "policies": {"planner": {"kind": "planner"}},
            "evaluation": {"episodes": 2, "seed": 0},
        }
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def listening() -> Iterator[int]:
    """A loopback port where something accepts TCP connections (but is no Ray head)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


@pytest.fixture
def no_ray_init(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """``ray.init`` replaced: records its calls (with the RAY_AUTH_MODE it saw) and refuses like a head that
    rejects the driver."""
    ray = pytest.importorskip("ray")
    calls: list[dict[str, Any]] = []

    def init(**kwargs: Any) -> None:
        import os

        calls.append({**kwargs, "RAY_AUTH_MODE": os.environ.get("RAY_AUTH_MODE")})
        raise ConnectionError(f"Failed to connect to Ray cluster at {kwargs.get('address')}")

    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    return calls


@pytest.mark.parametrize("scheme", ["", "ray://"])
def test_an_address_where_nothing_listens_is_refused_before_any_cell_starts(
    tmp_path: Path, scheme: str, no_ray_init: list[dict[str, Any]]
) -> None:
    cfg = _grid(tmp_path)
    port = _free_port()
    lines: list[str] = []
    with pytest.raises(ConfigError) as err:
        ab.run_grid(cfg, backend="ray", address=f"{scheme}127.0.0.1:{port}", out=lines.append)
    assert f"nothing accepts connections at 127.0.0.1:{port} " in str(err.value)
    assert f"TCP probe of {ab.CONNECT_TIMEOUT_S:g} s" in str(err.value) and "No cell was started" in str(err.value)
    assert no_ray_init == []  # Ray (which waits minutes there) was never asked
    assert not cfg.runs_path().exists() and not any(line.startswith("start") for line in lines)


def test_a_probe_passes_where_something_listens_and_bad_addresses_are_named(listening: int) -> None:
    ab.check_address(f"127.0.0.1:{listening}")
    ab.check_address(f"ray://127.0.0.1:{listening}")
    ab.check_address("auto")  # Ray finds the local cluster itself
    for bad in ("127.0.0.1", "127.0.0.1:port", "http://127.0.0.1:6379", "127.0.0.1:70000"):
        with pytest.raises(ConfigError, match=r"expected HOST:PORT"):
            ab.check_address(bad)


def test_a_failed_connection_is_one_message_saying_what_to_check(
    tmp_path: Path, listening: int, no_ray_init: list[dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    for var in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))  # no token anywhere
    cfg = _grid(tmp_path)
    with pytest.raises(ConfigError) as err:
        ab.run_grid(cfg, backend="ray", address=f"127.0.0.1:{listening}", out=lambda s: None)
    message = str(err.value)
    for words in (
        f"--address 127.0.0.1:{listening}: Ray could not connect (ConnectionError: Failed to connect",
        "same Ray and Python versions",
        "RAY_AUTH_MODE here: unset",
        "~/.ray/auth_token",
        "python -m agents.ablation --help",
    ):
        assert words in message
    assert "\n" not in message and no_ray_init[0]["RAY_AUTH_MODE"] is None
    assert not cfg.runs_path().exists()


def test_a_token_turns_token_authentication_on_as_ray_start_does(
    tmp_path: Path, listening: int, no_ray_init: list[dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    for var in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"):
        monkeypatch.delenv(var, raising=False)
    token = tmp_path / "home" / ".ray" / "auth_token"
    token.parent.mkdir(parents=True)
    token.write_text("0" * 32)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    lines: list[str] = []
    with pytest.raises(ConfigError, match="RAY_AUTH_MODE here: token"):
        ab.run_grid(_grid(tmp_path), backend="ray", address=f"127.0.0.1:{listening}", out=lines.append)
    assert no_ray_init[0]["RAY_AUTH_MODE"] == "token"
    assert any(f"token authentication on (token from {token}" in line for line in lines)
    # an explicit RAY_AUTH_MODE is left as it is
    no_ray_init.clear()
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    with pytest.raises(ConfigError, match="RAY_AUTH_MODE here: disabled"):
        ab.run_grid(_grid(tmp_path), backend="ray", address=f"127.0.0.1:{listening}", out=lambda s: None)
    assert no_ray_init[0]["RAY_AUTH_MODE"] == "disabled"


def _cell_with_checkpoints(folder: Path, pointer: int, complete: dict[int, bool]) -> None:
    """Checkpoint folders with a vecnormalize file their state lists; an incomplete one lacks its state file."""
    root = folder / ab.TRAIN_RUN / "checkpoints"
    for steps, whole in complete.items():
        step = root / f"step_{steps:010d}"
        step.mkdir(parents=True)
        (step / "model.zip").write_bytes(b"weights")
        (step / "model_vecnormalize.pkl").write_bytes(b"statistics")
        if whole:
            state = {"steps": steps, "files": ["model.zip", "model_vecnormalize.pkl"]}
            (step / "state.json").write_text(json.dumps(state))
    root.mkdir(parents=True, exist_ok=True)
    (root / "latest.json").write_text(json.dumps({"steps": pointer, "folder": f"step_{pointer:010d}"}))


def test_a_cell_folder_packed_mid_checkpoint_is_not_shipped(tmp_path: Path) -> None:
    # packed while the run wrote step 256: its pointer is there, its state file not yet
    _cell_with_checkpoints(tmp_path / "mid", 256, {128: True, 256: False})
    assert rb._archived_checkpoint(rb._pack(tmp_path / "mid")) is None
    # the driver still reports (and a resume uses) the complete step 128
    assert rb._checkpoint_steps(tmp_path / "mid") == 128
    _cell_with_checkpoints(tmp_path / "whole", 256, {256: True})
    assert rb._archived_checkpoint(rb._pack(tmp_path / "whole")) == 256
    # packed while the old checkpoint was pruned: a file its state lists is gone
    (tmp_path / "whole" / ab.TRAIN_RUN / "checkpoints" / "step_0000000256" / "model_vecnormalize.pkl").unlink()
    assert rb._archived_checkpoint(rb._pack(tmp_path / "whole")) is None


class _StubRay:
    """What ``_Shipper._ship`` uses of ray (``get``) and of the inbox actor (``put.remote``), recording puts."""

    def __init__(self) -> None:
        self.shipped: list[int] = []
        self.put = self
        self.inbox = self

    def remote(self, name: str, steps: int, blob: bytes) -> int:
        self.shipped.append(steps)
        return steps

    def get(self, ref: Any) -> Any:
        return ref


def test_the_shipper_ships_each_complete_checkpoint_once_and_never_a_half_written_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    stub = _StubRay()
    cell = tmp_path / "cell"
    shipper = object.__new__(rb._Shipper)  # without its thread and without ray
    shipper._ray, shipper.folder, shipper.name, shipper.inbox, shipper._last = stub, cell, "cell", stub, None
    _cell_with_checkpoints(cell, 128, {128: True})
    shipper._ship()
    shipper._ship()  # nothing new
    assert stub.shipped == [128]
    _cell_with_checkpoints(cell, 256, {256: True})
    # the folder as a pack caught it while step 256 was written: its pointer, not yet its state file
    _cell_with_checkpoints(tmp_path / "caught", 256, {128: True, 256: False})
    pack = rb._pack
    monkeypatch.setattr(rb, "_pack", lambda folder: pack(tmp_path / "caught"))
    shipper._ship()
    assert stub.shipped == [128]  # not shipped: the next look does
    monkeypatch.undo()
    shipper._ship()
    assert stub.shipped == [128, 256]


def test_packing_skips_checkpoints_being_written_or_replaced(tmp_path: Path) -> None:
    _cell_with_checkpoints(tmp_path, 64, {64: True})
    for name in (".step_0000000128.partial", ".step_0000000064.old"):
        (tmp_path / ab.TRAIN_RUN / "checkpoints" / name).mkdir()
        (tmp_path / ab.TRAIN_RUN / "checkpoints" / name / "model.zip").write_bytes(b"half")
    with tarfile.open(fileobj=io.BytesIO(rb._pack(tmp_path)), mode="r:gz") as tar:
        names = tar.getnames()
    assert not [n for n in names if ".partial" in n or ".old" in n]
    assert f"./{ab.TRAIN_RUN}/checkpoints/step_0000000064/state.json" in names
