"""The grid's cells as Ray tasks: connecting to a cluster, shipping cell folders, and training checkpoints.

Supported Ray
    ``pip install 'crowdnav-mesrnn[ray]'`` (``ray>=2.9``); tested with Ray 2.60, the version CI installs.
    Every node and the driver need the same Ray and Python versions (Ray refuses to connect otherwise).

Connecting (``--address``)
    ``HOST:PORT`` (the head's GCS port, 6379 by default: ``ray start --head --port 6379``) or
    ``ray://HOST:10001`` (Ray Client). Before anything else the address gets a TCP connection probe of
    :data:`CONNECT_TIMEOUT_S` seconds: where nothing listens the grid stops at once, no cell started. Ray then
    needs up to about 20 s to give up on a head that refuses it (wrong token, other Ray version); every
    failure of ``ray.init`` becomes one :class:`ConfigError` saying what to check.

Token authentication (Ray >= 2.52)
    ``ray start --head`` enables token authentication when a token exists (``RAY_AUTH_TOKEN``,
    ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``; Ray >= 2.59 creates ``~/.ray/auth_token`` whenever a
    local instance starts) and ``RAY_AUTH_MODE`` is unset. The driver does the same before it connects, and
    says so (a token-authenticated driver also joins a head without authentication); ``RAY_AUTH_MODE=disabled``
    turns it off. Every other node needs the same token (copy ``~/.ray/auth_token``, or set ``RAY_AUTH_TOKEN``).

Files and checkpoints
    No shared storage is needed: the driver sends what a cell needs with its task (an interrupted training
    run's folder, or the trained model being evaluated); the task works in a temporary folder on its node
    and returns the cell folder as a tar archive, which the driver writes into ``runs_dir``. While a training
    cell runs, each new checkpoint is shipped to the driver too (through a small actor, polled every
    :data:`CHECKPOINT_POLL_S` s) and written into the cell's folder, so a cell whose task is killed or
    cancelled resumes from its last checkpoint on the next run of the grid, as on the local backend. Tasks
    are not retried by Ray (a retry would start from the inputs of the first try). A task removes its
    temporary folder when it ends, and the folders of killed tasks on its node when it starts.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import shutil
import socket
import sys
import tarfile
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Final

from agents.ablation.cells import _read_json
from agents.ablation.config import CELL_JSON, TRAIN_RUN
from agents.ablation.execute import STOP_TIMEOUT_S, CellTask, _Backend, execute_cell
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.utils import atomic_write_json

#: Seconds the TCP probe of ``--address`` waits for a connection before the grid gives up.
CONNECT_TIMEOUT_S: Final[float] = 5.0

#: Seconds between two looks of a running training task for a new checkpoint to ship to the driver.
CHECKPOINT_POLL_S: Final[float] = 1.0

#: Prefix of a task's temporary folder: ``crowdnav-ablation-<pid>-<random>`` in the node's temporary directory.
TEMP_PREFIX: Final[str] = "crowdnav-ablation-"

_RAY_CLIENT_PORT: Final[int] = 10001


def ray_endpoint(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``--address`` (``HOST:PORT`` or ``ray://HOST[:PORT]``); None for ``auto``/``local``."""
    text = address.strip()
    if text in ("auto", "local"):
        return None
    scheme, _, rest = text.rpartition("://")
    host, sep, port = rest.rpartition(":")
    if not sep and scheme == "ray":
        host, port = rest, str(_RAY_CLIENT_PORT)
    if not host or not port.isdigit() or not 0 < int(port) < 65536 or scheme not in ("", "ray"):
        raise ConfigError(
            f"--address {address!r}: expected HOST:PORT (the head's port, e.g. 127.0.0.1:6379) or "
            f"ray://HOST:{_RAY_CLIENT_PORT}"
        )
    return host.strip("[]"), int(port)


def check_address(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Raise :class:`ConfigError` unless something accepts a TCP connection at ``address`` within ``timeout_s``."""
    endpoint = ray_endpoint(address)
    if endpoint is None:
        return
    host, port = endpoint
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        why = "no answer" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise ConfigError(
            f"--address {address}: nothing accepts connections at {host}:{port} ({why}; TCP probe of "
            f"{timeout_s:g} s). Start the head first (ray start --head --port {port}), or correct the address. "
            "No cell was started."
        ) from None


def _token_available() -> str | None:
    """Where Ray would read an authentication token from, if any (its own order)."""
    if os.environ.get("RAY_AUTH_TOKEN"):
        return "RAY_AUTH_TOKEN"
    path = os.environ.get("RAY_AUTH_TOKEN_PATH")
    if path:
        return path if Path(path).is_file() else None
    default = Path.home() / ".ray" / "auth_token"
    return str(default) if default.is_file() else None


def enable_token_auth(out: Callable[[str], None] = print) -> bool:
    """Token authentication for this driver when a token exists and ``RAY_AUTH_MODE`` is unset, as
    ``ray start`` does for a head; True when it was turned on here."""
    if os.environ.get("RAY_AUTH_MODE") is not None:
        return False
    source = _token_available()
    if source is None:
        return False
    os.environ["RAY_AUTH_MODE"] = "token"
    if "ray" in sys.modules:  # Ray read its settings when imported: have it read them again
        try:
            from ray._raylet import Config

            Config.initialize("")
        except (ImportError, AttributeError):  # a Ray without token authentication (< 2.52)
            pass
    out(
        f"Ray: token authentication on (token from {source}, as `ray start --head` uses it); "
        "RAY_AUTH_MODE=disabled connects without"
    )
    return True


def _connect_error(address: str, exc: BaseException) -> ConfigError:
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    mode = os.environ.get("RAY_AUTH_MODE", "unset")
    return ConfigError(
        f"--address {address}: Ray could not connect ({type(exc).__name__}: {first}). Check that: the head runs "
        f"the same Ray and Python versions as here (Ray {_ray_version()}); with token authentication (Ray >= 2.52, "
        f"RAY_AUTH_MODE here: {mode}) this machine has the head's token (~/.ray/auth_token, RAY_AUTH_TOKEN or "
        "RAY_AUTH_TOKEN_PATH); HOST:PORT is the head's GCS port (ray start --head --port 6379) or "
        f"ray://HOST:{_RAY_CLIENT_PORT} for Ray Client. Set-up: python -m agents.ablation --help."
    )


def _ray_version() -> str:
    try:
        import ray

        return str(ray.__version__)
    except ImportError:
        return "not installed"


# ---------------------------------------------------------------------------- files


def _pack(folder: Path) -> bytes:
    """A folder as gzipped tar bytes, files only, skipping temporary files (``.name.tmp``), checkpoints being
    written or replaced (``.step_<n>.partial``, ``.step_<n>.old``) and files that vanish while it is read (a
    training run replaces its old checkpoints)."""
    from agents.training.callbacks import STAGING_SUFFIXES

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for dirpath, dirnames, filenames in sorted(os.walk(folder)) if folder.is_dir() else []:
            dirnames.sort()
            parts = Path(dirpath).relative_to(folder).parts
            if any(p.startswith(".") and p.endswith(STAGING_SUFFIXES) for p in parts):
                continue
            for name in sorted(filenames):
                if name.startswith(".") and name.endswith(".tmp"):
                    continue
                path = Path(dirpath) / name
                try:
                    tar.add(path, arcname=f"./{path.relative_to(folder).as_posix()}")
                except FileNotFoundError:
                    continue
    return buf.getvalue()


def _unpack(blob: bytes, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(blob), mode="r:gz") as tar:
        tar.extractall(dest, filter="data")


def _replace_folder(folder: Path, blob: bytes) -> None:
    """Make ``folder`` hold exactly the archive's content, swapping it in with renames."""
    incoming = folder.parent / f".{folder.name}.incoming"
    old = folder.parent / f".{folder.name}.old"
    for tmp in (incoming, old):
        shutil.rmtree(tmp, ignore_errors=True)
    _unpack(blob, incoming)
    if folder.exists():
        folder.rename(old)
    incoming.rename(folder)
    shutil.rmtree(old, ignore_errors=True)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_temp_folders(root: str | os.PathLike[str] | None = None) -> list[Path]:
    """Remove the temporary folders of tasks whose process is gone (killed before it could clean up);
    returns them. ``root``: the temporary directory (default: this node's)."""
    removed = []
    for path in Path(root or tempfile.gettempdir()).glob(f"{TEMP_PREFIX}*-*"):
        pid = path.name.removeprefix(TEMP_PREFIX).split("-", 1)[0]
        if path.is_dir() and pid.isdigit() and not _pid_alive(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


class _Inbox:
    """A Ray actor holding the latest checkpointed folder of each running training cell until the driver takes it."""

    def __init__(self) -> None:
        self._latest: dict[str, tuple[int, bytes]] = {}

    def put(self, name: str, steps: int, blob: bytes) -> None:
        self._latest[name] = (steps, blob)

    def take(self) -> dict[str, tuple[int, bytes]]:
        out, self._latest = self._latest, {}
        return out


def _checkpoint_steps(folder: Path) -> int | None:
    """The step of the cell folder's checkpoint a resume would use (the latest complete one), or None."""
    from agents.training.callbacks import latest_checkpoint

    ckpt = latest_checkpoint(folder / TRAIN_RUN)
    steps = (_read_json(ckpt / "state.json") or {}).get("steps") if ckpt is not None else None
    return int(steps) if isinstance(steps, int) else None


def _archived_checkpoint(blob: bytes) -> int | None:
    """The step of the checkpoint ``checkpoints/latest.json`` points at in a packed cell folder, if that
    checkpoint is complete in the archive (``agents.training.callbacks.checkpoint_required_files``: the rule on
    disk); else None. A folder packed while the run wrote a new checkpoint can hold a pointer to a folder it caught
    half-written or removed: such an archive is not shipped."""
    from agents.training.callbacks import checkpoint_required_files

    root = f"./{TRAIN_RUN}/checkpoints"

    def member_json(tar: tarfile.TarFile, name: str) -> Any:
        try:
            member = tar.extractfile(name)
            return json.loads(member.read()) if member is not None else None
        except (KeyError, ValueError):
            return None

    with tarfile.open(fileobj=io.BytesIO(blob), mode="r:gz") as tar:
        names = set(tar.getnames())
        latest = member_json(tar, f"{root}/latest.json")
        if not isinstance(latest, dict) or not isinstance(latest.get("folder"), str):
            return None
        folder = f"{root}/{latest['folder']}"
        state = member_json(tar, f"{folder}/state.json")
    required = checkpoint_required_files(state)
    if required is None or not all(f"{folder}/{name}" in names for name in required):
        return None
    steps = latest.get("steps")
    return int(steps) if isinstance(steps, int) else None


class _Shipper:
    """In a training task: a thread that ships the cell folder to the driver's inbox at every new checkpoint."""

    def __init__(self, folder: Path, name: str, inbox: Any) -> None:
        import ray

        self._ray, self.folder, self.name, self.inbox = ray, folder, name, inbox
        self._last = _checkpoint_steps(folder)  # resumed from it: the driver has it already
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="checkpoint-shipper", daemon=True)
        self._thread.start()

    def _ship(self) -> None:
        steps = _checkpoint_steps(self.folder)
        if steps is None or steps == self._last:
            return
        from agents.training.callbacks import CHECKPOINT_LOCK

        with CHECKPOINT_LOCK:  # the training run in this process does not save or prune while it is read
            blob = _pack(self.folder)
        steps = _archived_checkpoint(blob)
        if steps is None or steps == self._last:  # caught mid-write: the next look ships it
            return
        self._ray.get(self.inbox.put.remote(self.name, steps, blob))
        self._last = steps

    def _run(self) -> None:
        while not self._stop.wait(CHECKPOINT_POLL_S):
            try:
                self._ship()
            except Exception:  # a folder changing while it is read: the next look ships it
                continue

    def close(self) -> None:
        """Stop, then ship a checkpoint written since the last look (the one of an interrupt)."""
        self._stop.set()
        self._thread.join()
        try:
            self._ship()
        except Exception:
            pass


def execute_shipped(task: CellTask, inputs: bytes | None, inbox: Any = None) -> tuple[dict[str, Any], bytes]:
    """A Ray task: run the cell in a temporary folder on this node and return its folder as tar bytes.

    ``inputs`` (tar bytes) holds ``cell/`` (an interrupted training run to resume) and/or ``model/`` (the
    trained run folder whose model is evaluated); paths in ``task`` are rewritten to the temporary copies.
    With an ``inbox`` (:class:`_Inbox` actor), a training cell's checkpoints are shipped as they are written.
    """
    sweep_temp_folders()
    root = Path(tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}{os.getpid()}-"))
    try:
        if inputs:
            _unpack(inputs, root)
        folder = root / "cell"
        model = None
        if task.model is not None:
            model = str(root / "model" / Path(task.model).name)
        local = dataclasses.replace(task, folder=str(folder), model=model)
        shipper = _Shipper(folder, task.cell.name, inbox) if inbox is not None and task.cell.kind == "train" else None
        try:
            result = execute_cell(local)
        finally:
            if shipper is not None:
                shipper.close()
        if task.model is not None:  # record the driver's path, not the temporary one
            meta = _read_json(folder / CELL_JSON) or {}
            meta["model"] = task.model
            atomic_write_json(folder / CELL_JSON, meta)
        return result, _pack(folder)
    finally:
        shutil.rmtree(root, ignore_errors=True)


def _shipped_inputs(task: CellTask) -> bytes | None:
    buf = io.BytesIO()
    added = False
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        folder = Path(task.folder)
        if task.cell.kind == "train" and folder.is_dir():
            tar.add(folder, arcname="cell")
            added = True
        if task.model is not None:
            run = Path(task.model).parent
            for path in sorted(run.iterdir()):
                if path.is_file():  # the run's top-level files: models, resolved config; not checkpoints/logs
                    tar.add(path, arcname=f"model/{path.name}")
            added = True
    return buf.getvalue() if added else None


# ---------------------------------------------------------------------------- the backend


class RayBackend(_Backend):
    """Cells as Ray tasks on a cluster (``address``) or a local instance of ``num_cpus`` CPUs."""

    def __init__(self, address: str | None, num_cpus: int | None, out: Callable[[str], None] = print) -> None:
        if address:
            check_address(address)
            enable_token_auth(out)
        try:
            import ray
        except ImportError as exc:
            raise ConfigError(
                "--backend ray needs Ray: pip install 'crowdnav-mesrnn[ray]' (or pip install 'ray>=2.9')"
            ) from exc
        self._ray, self._out = ray, out
        self._started = not ray.is_initialized()
        if self._started:
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True}
            if address:
                kwargs["address"] = address
                kwargs["runtime_env"] = {"env_vars": {"OMP_NUM_THREADS": "1"}}
            elif num_cpus:
                kwargs["num_cpus"] = num_cpus
            try:
                ray.init(**kwargs)
            except Exception as exc:  # ConnectionError, version mismatch, authentication: one message
                ray.shutdown()
                if not address:
                    raise
                raise _connect_error(address, exc) from None
        self._remote = ray.remote(execute_shipped)
        self._inbox = ray.remote(_Inbox).options(num_cpus=0).remote()
        self._tasks: dict[Any, CellTask] = {}

    def submit(self, task: CellTask) -> Any:
        ref = self._remote.options(num_cpus=task.cell.cpus, max_retries=0).remote(
            task, _shipped_inputs(task), self._inbox
        )
        self._tasks[ref] = task
        return ref

    def _receive(self) -> None:
        """Write the checkpoints shipped since the last look into the folders of cells still running."""
        running = {t.cell.name: t for t in self._tasks.values()}
        for name, (steps, blob) in self._ray.get(self._inbox.take.remote()).items():
            if name in running:
                _replace_folder(Path(running[name].folder), blob)
                self._out(f"checkpoint {name} at step {steps:,} saved in {running[name].folder}")

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:
        refs = list(handles)
        while True:
            ready, _ = self._ray.wait(refs, num_returns=1, timeout=CHECKPOINT_POLL_S)
            self._receive()
            if ready:
                break
        ref = ready[0]
        task = self._tasks.pop(ref)
        try:
            result, blob = self._ray.get(ref)
        except Exception as exc:  # the task itself died (node lost, worker killed) or was cancelled
            last = _checkpoint_steps(Path(task.folder))
            resume = f"; its last checkpoint (step {last:,}) is in {task.folder}" if last is not None else ""
            error = f"ray task failed: {type(exc).__name__}: {str(exc).strip().splitlines()[0]}{resume}"
            return ref, {"name": task.cell.name, "ok": False, "error": error}
        _replace_folder(Path(task.folder), blob)
        return ref, result

    def stop(self, handles: Mapping[Any, Any]) -> None:
        """Cancel the running tasks (a KeyboardInterrupt in each: training checkpoints at its round boundary)
        and collect the checkpoints they ship, for up to :data:`STOP_TIMEOUT_S` s."""
        refs = [r for r in handles if r in self._tasks]
        for ref in refs:
            self._ray.cancel(ref)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        while refs and time.monotonic() < deadline:
            _, refs = self._ray.wait(refs, num_returns=len(refs), timeout=CHECKPOINT_POLL_S)
            self._receive()
        self._receive()

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
