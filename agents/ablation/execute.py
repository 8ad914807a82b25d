"""One cell of the grid run in its folder, and the interface every backend implements.

:func:`execute_cell` is what the local backends (:mod:`agents.ablation.backends`: in this process, or a process
pool) and the Ray backend (:mod:`agents.ablation.ray_backend`) run for a cell: it writes ``cell.json`` first,
trains (:func:`agents.training.run.train`) or evaluates (:func:`agents.evaluation.run.evaluate`), then writes
``cell.json`` again and, when the work succeeded, ``DONE``. It never raises for a failure of the work itself, so
one failed cell does not stop the grid. A backend (:class:`_Backend`) submits :class:`CellTask` objects and hands
back their results one at a time.
"""

from __future__ import annotations

import os
import socket
import time
import traceback
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from agents.ablation.cells import Cell, _now, _read_json, weights_fingerprint
from agents.ablation.config import AGENT_CONFIG, CELL_JSON, DONE, TRAIN_RUN, training_overrides
from agents.ablation.episodes import read_episodes
from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text, code_version

#: Seconds a second Ctrl-C waits for the stopped cells to write their checkpoint and ``cell.json``.
STOP_TIMEOUT_S: Final[float] = 60.0


@dataclass(frozen=True)
class CellTask:
    """What a worker needs to run one cell (picklable; paths are absolute or relative to the worker's cwd)."""

    cell: Cell
    folder: str
    spec: Mapping[str, Any]
    weights: Mapping[str, str]
    episodes: int
    eval_seed: int
    env: Mapping[str, Any]
    episodes_from: str = "test"
    """Evaluation: ``test`` (the held-out scene) or ``val`` (the training scenes' validation period)."""
    model: str | None = None
    """Evaluation of a learned policy: the model zip to evaluate."""
    model_sha256: str | None = None
    command: str = ""
    """The command line that reproduces the cell (recorded in a training run's ``command.txt``)."""
    agent_config: str | None = None
    """Training: the agent YAML's text (written into the cell as :data:`AGENT_CONFIG` and read from there,
    so a worker on another machine needs no copy of the driver's files)."""


def train_overrides(cell: Cell, env: Mapping[str, Any]) -> dict[str, Any]:
    """Overrides of ``agents.training.config.load_train_config`` for a training cell (:func:`training_overrides`)."""
    return training_overrides(cell.policy, cell.arm, cell.split, cell.seed, env)


def _run_train(task: CellTask, folder: Path) -> dict[str, Any]:
    """Train (or resume) one learned policy into ``folder / run``; returns counts for ``cell.json``."""
    from agents.training.config import load_train_config
    from agents.training.run import train

    cfg = load_train_config(folder / AGENT_CONFIG, None, train_overrides(task.cell, task.env))
    run = folder / TRAIN_RUN
    result = train(cfg, run, resume=run.exists(), progress=False, command=task.command)
    return {
        "run_dir": Path(result).resolve().relative_to(folder.resolve()).as_posix(),
        "steps": task.cell.policy.timesteps,
    }


def _run_eval(task: CellTask, folder: Path) -> dict[str, Any]:
    """Evaluate a trained model or a planner on the held-out scene (or, ``episodes_from="val"``, the training scenes'
    validation period); writes episodes.csv and summary.json."""
    from agents.evaluation.run import evaluate

    cell = task.cell
    spec = task.model if cell.policy.learned else cell.policy.kind
    options = {**dict(cell.policy.options), **cell.arm.planner_options()}  # an uncertainty or samples arm's option
    result = evaluate(
        spec,
        cell.arm.predictor,
        cell.split,
        task.episodes,
        seed=task.eval_seed,
        episodes_from=task.episodes_from,
        out_dir=folder,
        env_overrides={**task.env, **cell.arm.env_overrides()} or None,
        **({"planner_kwargs": options} if options else {}),
    )
    rows = read_episodes(folder / "episodes.csv")
    steps = sum(int(float(r.get("steps", 0) or 0)) for r in rows) if rows and "steps" in rows[0] else None
    return {"episodes": int(result.get("episodes", len(rows))), "steps": steps}


def execute_cell(task: CellTask) -> dict[str, Any]:
    """Run one cell in ``task.folder``: ``cell.json`` first, the work, then ``cell.json`` again and ``DONE``.

    Never raises for a failure of the work itself: the result (also in ``cell.json``) says ``ok`` and
    ``error``, so one failed cell does not stop the grid.
    """
    _single_thread()
    folder = Path(task.folder)
    folder.mkdir(parents=True, exist_ok=True)
    here = weights_fingerprint(task.cell.arm.predictor)
    if here != dict(task.weights):  # a Ray node with another installation than the driver's
        error = f"predictor weights on {socket.gethostname()} differ from the driver's: {here} != {dict(task.weights)}"
        return {"name": task.cell.name, "ok": False, "error": error, "wall_s": 0.0}
    old = _read_json(folder / CELL_JSON) or {}
    attempts = list(old.get("attempts", [])) if old.get("spec") == task.spec else []
    meta: dict[str, Any] = {
        "name": task.cell.name,
        "spec": dict(task.spec),
        "weights": dict(task.weights),
        "model": task.model,
        "model_sha256": task.model_sha256,
        "code_version": code_version(),
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "status": "running",
        "attempts": [*attempts, {"started": _now()}],
    }
    atomic_write_json(folder / CELL_JSON, meta)
    if task.agent_config is not None:
        atomic_write_text(folder / AGENT_CONFIG, task.agent_config)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    try:
        counts = _run_train(task, folder) if task.cell.kind == "train" else _run_eval(task, folder)
        ok, error = True, None
    except Exception as exc:  # report and carry on with the other cells
        counts, ok = {}, False
        error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"
    except KeyboardInterrupt:  # stopped (a second Ctrl-C, SIGTERM, ray.cancel): record the attempt, then stop
        _finish_attempt(meta, time.perf_counter() - t0, False, "interrupted", _cpu_seconds() - c0)
        atomic_write_json(folder / CELL_JSON, meta)
        raise
    wall = time.perf_counter() - t0
    _finish_attempt(meta, wall, ok, "done" if ok else "failed", _cpu_seconds() - c0)
    meta.update(counts)
    meta["error"] = error
    if ok:
        cpu = meta.get("cpu_s")
        if task.cell.kind == "train" and meta.get("steps"):
            meta["steps_per_s"] = meta["steps"] / max(meta["wall_s"], 1e-9)
            if cpu:
                meta["steps_per_cpu_s"] = meta["steps"] / max(cpu, 1e-9)
        if task.cell.kind == "eval":
            meta["episodes_per_s"] = meta.get("episodes", task.episodes) / max(wall, 1e-9)
            meta["episodes_per_cpu_s"] = meta.get("episodes", task.episodes) / max(meta["attempts"][-1]["cpu_s"], 1e-9)
    atomic_write_json(folder / CELL_JSON, meta)
    if ok:
        atomic_write_text(folder / DONE, _now() + "\n")
    return {"name": task.cell.name, "ok": ok, "error": error, "wall_s": wall}


def _finish_attempt(meta: dict[str, Any], wall: float, ok: bool, status: str, cpu: float) -> None:
    """Close the last attempt of a cell's ``cell.json`` content: its end, wall time, CPU time and status. The cell's
    ``cpu_s`` is the sum over its attempts when every attempt recorded one (attempts before CPU time was recorded:
    none)."""
    meta["attempts"][-1].update(finished=_now(), wall_s=round(wall, 3), cpu_s=round(cpu, 3), ok=ok)
    meta["wall_s"] = round(sum(a.get("wall_s", 0.0) for a in meta["attempts"]), 3)
    cpus = [a.get("cpu_s") for a in meta["attempts"]]
    meta["cpu_s"] = round(sum(cpus), 3) if all(isinstance(c, int | float) for c in cpus) else None
    meta["status"] = status


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of the child processes it has waited for (a training run's
    subprocess environments): a cell's cost whatever else shares the machine, unlike its wall time."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _single_thread() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


class _Backend:
    """How the grid runs cells: :meth:`submit` a task, :meth:`wait_one` for the next result, :meth:`stop` the
    running cells, :meth:`close`."""

    #: How many cells it runs at once (``None``: it queues whatever is submitted, e.g. Ray). The grid submits no more
    #: than this, so a cell that waits is never handed to the backend: a first Ctrl-C then starts no other cell.
    capacity: int | None = None

    def submit(self, task: CellTask) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:  # pragma: no cover - interface
        raise NotImplementedError

    def stop(self, handles: Mapping[Any, Any]) -> None:
        """Stop the running cells now (a KeyboardInterrupt in each) and wait for them to record it."""

    def close(self) -> None:
        pass
