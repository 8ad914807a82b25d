"""Running cells: one cell in a folder, the serial/process-pool/Ray backends, the grid, and replication."""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import socket
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from agents.ablation.cells import (
    Cell,
    CellStatus,
    _file_sha256,
    _hms,
    _now,
    _read_json,
    cell_dir,
    cell_spec,
    default_workers,
    expand,
    plan,
    select,
    trained_model,
    weights_fingerprint,
)
from agents.ablation.config import (
    AGENT_CONFIG,
    BACKENDS,
    CELL_JSON,
    DONE,
    LEARNED_SOURCES,
    TRAIN_RUN,
    AblationConfig,
    training_overrides,
)
from agents.ablation.episodes import read_episodes
from agents.ablation.results import ResultsKept
from agents.ablation.summary import summarize
from crowdnav_mesrnn.config import ConfigError
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
    """Evaluate a trained model or a planner on the held-out scene; writes episodes.csv and summary.json."""
    from agents.evaluation.run import evaluate

    cell = task.cell
    spec = task.model if cell.policy.learned else cell.policy.kind
    options = {**dict(cell.policy.options), **cell.arm.planner_options()}  # an uncertainty arm: uncertainty=True
    result = evaluate(
        spec,
        cell.arm.predictor,
        cell.split,
        task.episodes,
        seed=task.eval_seed,
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
    t0 = time.perf_counter()
    try:
        counts = _run_train(task, folder) if task.cell.kind == "train" else _run_eval(task, folder)
        ok, error = True, None
    except Exception as exc:  # report and carry on with the other cells
        counts, ok = {}, False
        error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"
    except KeyboardInterrupt:  # stopped (a second Ctrl-C, SIGTERM, ray.cancel): record the attempt, then stop
        _finish_attempt(meta, time.perf_counter() - t0, False, "interrupted")
        atomic_write_json(folder / CELL_JSON, meta)
        raise
    wall = time.perf_counter() - t0
    _finish_attempt(meta, wall, ok, "done" if ok else "failed")
    meta.update(counts)
    meta["error"] = error
    if ok:
        if task.cell.kind == "train" and meta.get("steps"):
            meta["steps_per_s"] = meta["steps"] / max(meta["wall_s"], 1e-9)
        if task.cell.kind == "eval":
            meta["episodes_per_s"] = meta.get("episodes", task.episodes) / max(wall, 1e-9)
    atomic_write_json(folder / CELL_JSON, meta)
    if ok:
        atomic_write_text(folder / DONE, _now() + "\n")
    return {"name": task.cell.name, "ok": ok, "error": error, "wall_s": wall}


def _finish_attempt(meta: dict[str, Any], wall: float, ok: bool, status: str) -> None:
    """Close the last attempt of a cell's ``cell.json`` content: its end, wall time and status."""
    meta["attempts"][-1].update(finished=_now(), wall_s=round(wall, 3), ok=ok)
    meta["wall_s"] = round(sum(a.get("wall_s", 0.0) for a in meta["attempts"]), 3)
    meta["status"] = status


def _single_thread() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


class _Backend:
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


class _Serial(_Backend):
    """Cells one after another in this process (``--workers 1``); a second Ctrl-C stops the cell itself."""

    capacity = 1

    def __init__(self) -> None:
        self._results: dict[int, dict[str, Any]] = {}
        self._next = 0

    def submit(self, task: CellTask) -> Any:
        self._next += 1
        self._results[self._next] = execute_cell(task)
        return self._next

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:
        handle = next(iter(handles))
        return handle, self._results.pop(handle)


def _pool_worker() -> None:
    """A pool worker: one torch thread; Ctrl-C is the main process's to handle (the terminal sends it to the
    whole process group), SIGTERM -- how the main process stops a cell now -- interrupts the cell."""
    _single_thread()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.default_int_handler)


class _Pool(_Backend):
    """A process pool with forkserver (or spawn) workers, one torch thread each."""

    def __init__(self, workers: int) -> None:
        import concurrent.futures as cf
        import multiprocessing as mp

        method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        self._cf = cf
        # a fresh process per cell (max_tasks_per_child=1): a long grid measured its two reused workers growing to
        # 5.6 and 6.8 GB after six training cells each; a new process costs a second of imports per cell
        self._pool = cf.ProcessPoolExecutor(
            workers, mp_context=mp.get_context(method), initializer=_pool_worker, max_tasks_per_child=1
        )
        self.capacity = workers
        self._tasks: dict[Any, CellTask] = {}

    def submit(self, task: CellTask) -> Any:
        fut = self._pool.submit(execute_cell, task)
        self._tasks[fut] = task
        return fut

    def wait_one(self, handles: Iterable[Any]) -> tuple[Any, dict[str, Any]]:
        done, _ = self._cf.wait(list(handles), return_when=self._cf.FIRST_COMPLETED)
        fut = next(iter(done))
        self._tasks.pop(fut, None)
        try:
            return fut, fut.result()
        except BaseException as exc:  # a worker died (killed, out of memory) or was stopped: the cell stays partial
            return fut, {"ok": False, "error": f"worker failed: {type(exc).__name__}: {exc}"}

    def stop(self, handles: Mapping[Any, Any]) -> None:
        """SIGTERM to the worker of each running cell (its pid is in the cell's ``cell.json``): a KeyboardInterrupt
        there, so a training run checkpoints its last round boundary; then wait for them."""
        futures = [f for f in handles if f in self._tasks and not f.done()]
        for fut in futures:
            pid = (_read_json(Path(self._tasks[fut].folder) / CELL_JSON) or {}).get("pid")
            if isinstance(pid, int) and pid in getattr(self._pool, "_processes", {}):
                os.kill(pid, signal.SIGTERM)
        self._cf.wait(futures, timeout=STOP_TIMEOUT_S)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class _Interrupts:
    """Ctrl-C (SIGINT) while a grid runs: the first lets the running cells finish, starts no other, and says
    which it waits for; the second stops them now (``KeyboardInterrupt``). In the main thread only."""

    def __init__(self, out: Callable[[str], None]) -> None:
        self.out = out
        self.count = 0
        self.running: list[str] = []
        self._previous: Any = None

    def __enter__(self) -> _Interrupts:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)

    def _handle(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.count > 1 or not self.running:
            raise KeyboardInterrupt
        self.out(
            f"\ninterrupted: no other cell starts; waiting for the {len(self.running)} running cell(s) to finish: "
            f"{', '.join(sorted(self.running))}. Interrupt again (Ctrl-C) to stop them now: a training run keeps "
            "its last checkpoint and resumes from it, an evaluation starts over."
        )


def _prepare(cfg: AblationConfig, status: CellStatus) -> None:
    """Clear what must not be reused: stale cells, interrupted evaluations (interrupted training resumes)."""
    folder = cell_dir(cfg, status.cell)
    resumable = status.state == "partial" and status.cell.kind == "train" and status.meta is not None
    if status.state in ("stale", "partial") and not resumable and folder.exists():
        shutil.rmtree(folder)


def _task(cfg: AblationConfig, cell: Cell) -> CellTask:
    model = model_sha = None
    if cell.needs is not None:
        path = trained_model(cell_dir(cfg, cell.needs), cell.policy.model)
        if path is None:
            raise FileNotFoundError(f"{cell.needs} has no {cell.policy.model} model in {cell_dir(cfg, cell.needs)}")
        model, model_sha = str(path.resolve()), _file_sha256(path)
    return CellTask(
        cell=cell,
        folder=str(cell_dir(cfg, cell).resolve()),
        spec=cell_spec(cfg, cell),
        weights=weights_fingerprint(cell.arm.predictor),
        episodes=cfg.episodes,
        eval_seed=cfg.eval_seed,
        env=dict(cfg.env),
        model=model,
        model_sha256=model_sha,
        command=f"python -m agents.ablation {cfg.source or '<config>'} --only {cell.name}",
        agent_config=Path(cell.policy.config).read_text(encoding="utf-8") if cell.kind == "train" else None,
    )


def build_forecast_caches(
    cfg: AblationConfig, cells: Iterable[Cell], out: Callable[[str], None] = print
) -> list[tuple[str, str]]:
    """Build the shared on-disk forecast cache once for every (learned source, split) the cells need (an
    uncertainty arm uses its source's forecasts, so ``mesrnn`` and ``mesrnn_unc`` share one cache).

    Uses ``envs.forecasts.build_forecast_cache`` when the environment provides it (otherwise each process
    computes the forecasts it needs). Returns the pairs built.
    """
    import envs.forecasts as forecasts
    from envs.config import is_plugin_source

    wanted = sorted(
        {
            (c.arm.predictor, c.split)
            for c in cells
            if c.arm.predictor in LEARNED_SOURCES or is_plugin_source(c.arm.predictor)
        }
    )
    build = getattr(forecasts, "build_forecast_cache", None)
    if not wanted:
        return []
    if build is None:
        out("note: envs.forecasts.build_forecast_cache is not available; every worker computes its own forecasts")
        return []
    for predictor, split in wanted:
        t0 = time.perf_counter()
        build(predictor, split=split, part="all")
        out(f"forecast cache {predictor}/{split} ready ({time.perf_counter() - t0:.1f} s)")
    return wanted


def run_grid(
    cfg: AblationConfig,
    *,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    only: str | None = None,
    summarize_after: bool = True,
    force: bool = False,
    out: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run every cell that is not done (training before its evaluations) and summarise (``force``: see
    :func:`agents.ablation.summarize`; a summary that may not replace the results is reported, not raised).

    Ctrl-C: the first lets the running cells finish and starts no other (the cells left are ``interrupted``,
    no summary is written), the second stops the running cells now and raises ``KeyboardInterrupt``.

    Returns ``{"ran": [...], "failed": {name: error}, "skipped": [...], "interrupted": [...], "wall_s": ...,
    "summary": "written" | "kept" | None}``.
    """
    if backend not in BACKENDS:
        raise ConfigError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    t_start = time.perf_counter()
    cells = select(expand(cfg), only)
    workers = workers or default_workers(cells)
    statuses = plan(cfg, cells)
    todo = [s for s in statuses if s.state != "done"]
    out(f"grid {cfg.name}: {len(cells)} cells, {len(cells) - len(todo)} done, {len(todo)} to run ({backend} backend)")
    for policy in {s.cell.policy.name: s.cell.policy for s in todo if s.cell.policy.learned}.values():
        if not Path(policy.config or "").is_file():
            raise FileNotFoundError(f"policies.{policy.name}.config: agent config {policy.config!r} not found")
    waiting = {s.cell.name: s.cell for s in todo}
    runner = _runner(backend, workers, address, waiting.values(), out) if waiting else _Serial()
    done_names = {s.cell.name for s in statuses if s.state == "done"}
    ran: list[str] = []
    failed: dict[str, str] = {}
    skipped: list[str] = []
    running: dict[Any, Cell] = {}
    with _Interrupts(out) as interrupts:
        try:
            for st in todo:
                _prepare(cfg, st)
            build_forecast_caches(cfg, [s.cell for s in todo], out=out)
            while waiting or running:
                ready = [c for c in waiting.values() if c.needs is None or c.needs in done_names]
                for cell in ready:
                    if interrupts.count:  # after a Ctrl-C (with --workers 1, perhaps during the previous cell)
                        break
                    if runner.capacity is not None and len(running) >= runner.capacity:
                        break  # the rest waits here, not in the backend's queue
                    del waiting[cell.name]
                    out(f"start {cell.name}")
                    interrupts.running.append(cell.name)
                    running[runner.submit(_task(cfg, cell))] = cell
                if not running:  # what waits depends on failed cells, or was not started after a Ctrl-C
                    if not interrupts.count:
                        skipped.extend(sorted(waiting))
                    break
                handle, result = runner.wait_one(running)
                cell = running.pop(handle)
                interrupts.running.remove(cell.name)
                if result.get("ok"):
                    done_names.add(cell.name)
                    ran.append(cell.name)
                    out(f"done  {cell.name} ({_hms(float(result.get('wall_s', 0.0)))})")
                else:
                    failed[cell.name] = str(result.get("error"))
                    out(f"FAILED {cell.name}: {str(result.get('error')).splitlines()[0]}")
                    for name in [n for n, c in waiting.items() if c.needs == cell.name]:
                        skipped.append(waiting.pop(name).name)
        except KeyboardInterrupt:
            stopping = sorted(interrupts.running)
            if stopping:
                out(f"stopping {len(stopping)} running cell(s) now: {', '.join(stopping)}")
                runner.stop(running)
            out(
                f"grid {cfg.name} stopped; {len(ran)} cell(s) finished in this run. Run it again to go on: "
                "finished cells are kept, a stopped training run resumes from its last checkpoint."
            )
            raise
        finally:
            runner.close()
    wall = time.perf_counter() - t_start
    not_started = sorted(waiting) if interrupts.count else []
    out(
        f"grid {cfg.name}: ran {len(ran)}, failed {len(failed)}, skipped {len(skipped)}"
        + (f", not started after the interrupt {len(not_started)}" if not_started else "")
        + f" in {_hms(wall)}"
    )
    summary = None
    if summarize_after and not not_started:
        try:
            summarize(cfg, out=out, force=force)
            summary = "written"
        except ResultsKept as kept:
            out(str(kept))
            summary = "kept"
    elif summarize_after:
        out("summary not updated (interrupted); python -m agents.ablation CONFIG --summarize-only writes it")
    return {
        "ran": ran,
        "failed": failed,
        "skipped": skipped,
        "interrupted": not_started,
        "wall_s": wall,
        "summary": summary,
    }


def _runner(
    backend: str, workers: int, address: str | None, cells: Iterable[Cell], out: Callable[[str], None]
) -> _Backend:
    """The backend that runs the cells; on Ray, the cluster is reached (or the address refused) here, before
    any cell folder is touched."""
    if backend == "ray":
        from agents.ablation.ray_backend import RayBackend

        widest = max((c.cpus for c in cells), default=1)
        return RayBackend(address, num_cpus=None if address else workers * widest, out=out)
    return _Serial() if workers <= 1 else _Pool(workers)


def replicate(
    cfg: AblationConfig,
    only: str,
    into: str | os.PathLike[str],
    workers: int | None = None,
    out: Callable[[str], None] = print,
) -> int:
    """Run the cells ``only`` selects (with the training runs their evaluations need) afresh in the empty
    scratch folder ``into``, then compare every replicated evaluation with the grid's own, episode by episode
    and column by column (outcome, times, distances, return, ...).

    Training and evaluation are seeded, so a replicate at the same code, seed and forecasts should give
    identical episodes; a difference points at nondeterminism or at a change of behaviour between the code
    that ran the grid's cell (``cells.json``) and this one. Only grid cells that are ``done`` (spec and
    weights as now) are compared. Returns the number of selected evaluations that failed, could not be
    compared, or differ.
    """
    cells = select(expand(cfg), only)  # adds the training run of every selected evaluation
    evals = [c for c in cells if c.kind == "eval"]
    if not evals:
        raise ConfigError(f"--only {only!r} selects no evaluation cell: there would be nothing to compare")
    into = Path(into).resolve()
    for own in (cfg.runs_path().resolve(), cfg.out_path().resolve()):
        if into.is_relative_to(own) or own.is_relative_to(into):
            raise ConfigError(
                f"--replicate {str(into)!r} overlaps the grid's folder {str(own)!r}; give a scratch folder"
            )
    if into.exists() and any(into.iterdir()):
        raise ConfigError(
            f"--replicate {str(into)!r} is not empty; give a new or empty folder (a replicate starts afresh)"
        )
    states = {st.cell.name: st for st in plan(cfg, evals)}
    scratch = dataclasses.replace(cfg, runs_dir=str(into / "runs"), out_dir=str(into / "results"))
    result = run_grid(scratch, workers=workers, only=",".join(c.name for c in cells), summarize_after=False, out=out)
    for name, error in result["failed"].items():
        out(f"failed: {name}\n{error}")
    differing = 0
    for cell in evals:
        grid = states[cell.name]
        ours = {(r.get("seed"), r["episode"]): r for r in read_episodes(cell_dir(scratch, cell) / "episodes.csv")}
        theirs = {(r.get("seed"), r["episode"]): r for r in read_episodes(cell_dir(cfg, cell) / "episodes.csv")}
        if grid.state != "done" or not theirs or not ours:
            why = f"the grid's cell is {grid.state}" + (f" ({grid.reason})" if grid.reason else "")
            out(
                f"{cell.name}: not compared: " + (why if grid.state != "done" or not theirs else "the replicate failed")
            )
            differing += 1
            continue
        columns = sorted(set(next(iter(ours.values()))) | set(next(iter(theirs.values()))))
        shared = sorted(set(ours) & set(theirs))
        same = sum(ours[k] == theirs[k] for k in shared)
        outcomes = sum(ours[k].get("outcome") == theirs[k].get("outcome") for k in shared)
        rate = {
            n: sum(e["outcome"] == "success" for e in side.values()) / len(side)
            for n, side in (("o", ours), ("t", theirs))
        }
        out(
            f"{cell.name}: {same}/{len(shared)} episodes identical in all {len(columns)} columns, "
            f"{outcomes}/{len(shared)} outcomes; {len(ours)} episodes here, {len(theirs)} in the grid; "
            f"success {100 * rate['o']:.1f} % here, {100 * rate['t']:.1f} % in the grid"
        )
        differing += same != len(shared) or len(ours) != len(theirs) or len(shared) != len(ours)
    return differing
