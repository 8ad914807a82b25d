"""Running the grid: the serial and process-pool backends (the Ray one is :mod:`agents.ablation.ray_backend`), the
grid itself, and replication. A cell runs as :func:`agents.ablation.execute.execute_cell`."""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from agents.ablation import execute
from agents.ablation.cells import (
    Cell,
    CellStatus,
    _file_sha256,
    _hms,
    _read_json,
    cell_dir,
    cell_spec,
    check_environments,
    default_workers,
    expand,
    select,
    trained_model,
    weights_fingerprint,
)
from agents.ablation.config import (
    BACKENDS,
    CELL_JSON,
    AblationConfig,
)
from agents.ablation.episodes import read_episodes
from agents.ablation.execute import STOP_TIMEOUT_S, CellTask, _Backend, _single_thread, execute_cell
from agents.ablation.results import ResultsKept, plan
from agents.ablation.summary import summarize
from crowdnav_mesrnn.config import ConfigError


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
        env=cfg.env_for(cell.policy),
        episodes_from=cfg.episodes_from,
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

    Uses ``envs.forecasting.build.build_forecast_cache`` when the environment provides it (otherwise each process
    computes the forecasts it needs). Returns the pairs built.
    """
    import envs.forecasting.build as forecasts
    from crowdnav_mesrnn import predictors

    wanted = sorted({(c.arm.predictor, c.split) for c in cells if predictors.per_split(c.arm.predictor)})
    build = getattr(forecasts, "build_forecast_cache", None)
    if not wanted:
        return []
    if build is None:
        out(
            "note: envs.forecasting.build.build_forecast_cache is not available; every worker computes its own "
            "forecasts"
        )
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
    committed = sum(bool(s.source) for s in statuses)
    out(
        f"grid {cfg.name}: {len(cells)} cells, {len(cells) - len(todo)} done"
        + (f" ({committed} of them from committed results)" if committed else "")
        + f", {len(todo)} to run ({backend} backend)"
    )
    check_environments(cfg, [s.cell for s in todo])
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
    # afresh: no committed results (the grid's own nor other grids') stand in for a cell there
    scratch = dataclasses.replace(cfg, runs_dir=str(into / "runs"), out_dir=str(into / "results"), reuse=())
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
            if grid.source:  # no episodes.csv to compare with, only the results' archive
                why = f"the grid's cell has no run folder (it is done {grid.reason})"
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


def __getattr__(name: str) -> Any:
    """``train_overrides`` moved to :mod:`agents.ablation.execute`: this path works for one release, with a warning."""
    if name == "train_overrides":
        warnings.warn(
            "agents.ablation.backends.train_overrides is deprecated and will be removed in the next release: import "
            "it from agents.ablation.execute (or agents.ablation)",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(execute, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
