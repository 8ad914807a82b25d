"""PPO training throughput (environment steps per second, updates included) per forecast arm, and where a step goes.

Run: ``python benchmarks/train_speed.py [--json] [--steps 8192] [--arms none mesrnn] [--vec-env vector dummy]
[--cells 64:vector 8:dummy] [--config configs/agent/ppo_scoring.yaml] [--split zara1] [--set key=value ...]``.

Each measurement builds the PPO of the config (``agents.training``: the same policy, networks and rollout buffer;
validation, checkpoints and the warm start off) on the split's training scenes, with ``n_steps`` scaled so that every
update sees the config's rollout size (``n_steps x n_envs``) when a cell changes ``n_envs``; fills the shared forecast
cache first (its time is printed, not counted); runs one warm-up rollout and update; then times ``--steps`` steps of
one ``model.learn`` call and splits it per environment step, from inside that run:

- ``env``: the vectorised environment's ``step`` (a ``VecEnv`` wrapper): environments, observations, the forecast
  lookup, the discrete action mapping, the resets of finished episodes;
- ``policy_forward``: the policy's forward pass in the rollouts (``policy.forward`` and the value of truncated
  episodes' last observations, ``predict_values``);
- ``update``: the PPO update (from a callback's rollout end to the next rollout start or the end of training), per
  sample: every collected step is one sample of one update;
- ``other``: the rest (rollout buffer, observation to tensor, callbacks, ``learn``'s set-up).

The split is given in wall microseconds (``split_us``: it sums to ``1e6 / steps_per_s``) and in this process's CPU
microseconds (``cpu_split_us``: steadier on a shared machine; with ``subproc`` workers it leaves out the workers'
environments).

``--vec-env`` sets how the environments run (default ``vector``, the batched environment; the recipes pin theirs to
keep committed grid cells' hashes, and every kind gives the same transitions): ``vector`` (``agents.batched_vec_env``),
``batched`` (single environments in this process, the wrappers' work batched: ``agents.vec_env``), ``dummy`` (SB3's
``DummyVecEnv`` over wrapped environments), ``subproc`` (one forkserver worker each). Several kinds are measured one
after another (``--vec-env vector dummy``). ``--cells N:KIND ...`` (table only) measures other numbers of environments.

``--json`` prints one object for the config's ``n_envs``::

    {"arms": {arm: steps/s}, "split_us": {arm: {"env", "policy_forward", "update", "other"}},
     "cpu_split_us": {...}, "arms_per_cpu_second": {arm: steps per CPU second}, "ratio_vs_none": {arm: none's steps/s
     / arm's}, "vec_env", "n_envs", "config", "scenes", "steps", "matmul_gflops", "cpu_count", "load_average":
     {"start", "end"}, "by_vec_env": {kind: {"arms", "split_us", ...}}}

``arms`` and ``split_us`` are the first ``--vec-env`` kind's; ``by_vec_env`` holds every kind's. The machine's float32
matmul peak on one thread (``benchmarks/_timing.py``), its CPU count and its load average before and after are printed
beside the figures: machines differ by up to 4x, so compare figures of one run (ratios), or read them against that
peak. Prints figures; never asserts on time.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from _timing import matmul_peak_gflops
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env.base_vec_env import VecEnvWrapper

from agents.entry import parse_set
from agents.scoring import attach_geometry_cache
from agents.training.config import (
    VEC_ENVS,
    _algo_class,
    algorithm_kwargs,
    load_train_config,
    policy_class,
    vec_env_kind,
)
from agents.training.run import make_vec_env, prepare_training_forecasts

torch.set_num_threads(1)

REPO = Path(__file__).resolve().parent.parent
PHASES = ("env", "policy_forward", "update", "other")
#: The shipped recipe (configs/ablation/learned.yaml's PPO); configs/agent/ppo.yaml is the previous grid's.
DEFAULT_CONFIG = REPO / "configs" / "agent" / "ppo_scoring.yaml"


class _Clock:
    """Wall and CPU seconds accumulated per phase."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.wall = dict.fromkeys(PHASES, 0.0)
        self.cpu = dict.fromkeys(PHASES, 0.0)

    def add(self, phase: str, wall_s: float, cpu_s: float) -> None:
        self.wall[phase] += wall_s
        self.cpu[phase] += cpu_s

    def timed(self, fn: Any, phase: str) -> Any:
        """``fn`` with its time added to ``phase``."""

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.add(phase, time.perf_counter() - w, time.process_time() - c)

        return wrapper


class TimedVecEnv(VecEnvWrapper):
    """A ``VecEnv`` passing everything through, adding the time of every ``step`` (``step_async`` and
    ``step_wait``) to its clock's ``env`` phase."""

    def __init__(self, venv: Any, clock: _Clock) -> None:
        super().__init__(venv)
        self.clock = clock

    def reset(self) -> Any:
        return self.venv.reset()

    def step_async(self, actions: Any) -> None:
        w, c = time.perf_counter(), time.process_time()
        self.venv.step_async(actions)
        self.clock.add("env", time.perf_counter() - w, time.process_time() - c)

    def step_wait(self) -> Any:
        w, c = time.perf_counter(), time.process_time()
        out = self.venv.step_wait()
        self.clock.add("env", time.perf_counter() - w, time.process_time() - c)
        return out


class UpdateTimer(BaseCallback):
    """Adds the time from each rollout's end to the next rollout's start (or the end of training) -- SB3 runs the
    update there -- to its clock's ``update`` phase."""

    def __init__(self, clock: _Clock) -> None:
        super().__init__()
        self.clock = clock
        self._ended: tuple[float, float] | None = None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self._ended = (time.perf_counter(), time.process_time())

    def _since_rollout_end(self) -> None:
        if self._ended is not None:
            self.clock.add("update", time.perf_counter() - self._ended[0], time.process_time() - self._ended[1])
            self._ended = None

    def _on_rollout_start(self) -> None:
        self._since_rollout_end()

    def _on_training_end(self) -> None:
        self._since_rollout_end()


def measure(
    config: Path,
    predictor: str,
    steps: int,
    split: str,
    extra: Mapping[str, Any],
    vec_env: str | None = None,
    n_envs: int | None = None,
) -> dict[str, Any]:
    """One arm in one cell: ``{"steps_per_s", "steps_per_cpu_s", "cache_fill_s", "vec_env", "n_envs", "split_us",
    "cpu_split_us"}`` (``split_us``/``cpu_split_us``: wall/CPU microseconds per environment step by phase, see the
    module docstring). ``vec_env``/``n_envs`` None: the config's own (with ``extra`` applied)."""
    base = load_train_config(config, None, dict(extra))
    n = base.n_envs if n_envs is None else n_envs
    overrides = {
        **extra,
        "predictor": predictor,
        "split": split,
        "n_envs": n,
        "vec_env": vec_env or base.vec_env,
        "n_timesteps": steps,
        "eval.episodes": 0,
        "checkpoint_freq_steps": 0,
        "pretrain": None,
    }
    if base.algo == "ppo" and n != base.n_envs:  # the config's rollout size, n_steps x n_envs
        overrides["n_steps"] = max(1, int(base.hyperparams.get("n_steps", 2048)) * base.n_envs // n)
    cfg = load_train_config(config, None, overrides)
    t0 = time.perf_counter()
    prepare_training_forecasts(cfg)
    cache_s = time.perf_counter() - t0
    clock = _Clock()
    venv = TimedVecEnv(make_vec_env(cfg), clock)
    try:
        model = _algo_class(cfg.algo)(
            policy_class(cfg.policy), venv, seed=0, verbose=0, device="cpu", **algorithm_kwargs(cfg)
        )
        attach_geometry_cache(model)
        for name in ("forward", "predict_values"):  # the policy's calls in the rollouts (the update calls neither)
            setattr(model.policy, name, clock.timed(getattr(model.policy, name), "policy_forward"))
        model.learn(int(cfg.hyperparams.get("n_steps", 2048)) * n if cfg.algo == "ppo" else 1000)  # warm-up
        clock.reset()
        start = model.num_timesteps
        w, c = time.perf_counter(), time.process_time()
        model.learn(steps, callback=UpdateTimer(clock), reset_num_timesteps=False)
        wall, cpu = time.perf_counter() - w, time.process_time() - c
        done = model.num_timesteps - start  # whole rollouts: at least ``steps``
    finally:
        venv.close()
    clock.wall["other"] = wall - sum(clock.wall.values())
    clock.cpu["other"] = cpu - sum(clock.cpu.values())
    return {
        "steps_per_s": done / wall,
        "steps_per_cpu_s": done / cpu,
        "cache_fill_s": cache_s,
        "vec_env": vec_env_kind(cfg)[0],
        "n_envs": n,
        "split_us": {k: round(1e6 * v / done, 1) for k, v in clock.wall.items()},
        "cpu_split_us": {k: round(1e6 * v / done, 1) for k, v in clock.cpu.items()},
    }


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def machine(matmul_repeats: int = 20) -> dict[str, Any]:
    """The machine beside the figures: float32 matmul peak on one thread (GFLOP/s), CPU count, load average."""
    peak = matmul_peak_gflops(torch.float32, threads=1, repeats=matmul_repeats)
    torch.set_num_threads(1)
    return {"matmul_gflops": round(peak, 1), "cpu_count": os.cpu_count(), "load_average": _load()}


def run_json(
    config: Path,
    arms: Sequence[str],
    vec_envs: Sequence[str],
    steps: int,
    split: str,
    extra: Mapping[str, Any],
    matmul_repeats: int = 20,
) -> dict[str, Any]:
    """The ``--json`` object (module docstring) for the config's ``n_envs``, each arm under each ``vec_envs`` kind."""
    host = machine(matmul_repeats)
    by_kind: dict[str, dict[str, Any]] = {}
    for kind in vec_envs:
        runs = {arm: measure(config, arm, steps, split, extra, vec_env=kind) for arm in arms}
        rates = {arm: r["steps_per_s"] for arm, r in runs.items()}
        by_kind[kind] = {
            "arms": {arm: round(r, 1) for arm, r in rates.items()},
            "split_us": {arm: r["split_us"] for arm, r in runs.items()},
            "cpu_split_us": {arm: r["cpu_split_us"] for arm, r in runs.items()},
            "arms_per_cpu_second": {arm: round(r["steps_per_cpu_s"], 1) for arm, r in runs.items()},
            "ratio_vs_none": {arm: round(rates["none"] / r, 3) for arm, r in rates.items()} if "none" in rates else {},
            "vec_env": next(iter(runs.values()))["vec_env"],
            "n_envs": next(iter(runs.values()))["n_envs"],
        }
    first = by_kind[vec_envs[0]]
    shown = config.relative_to(REPO) if config.is_relative_to(REPO) else config
    return {
        **first,
        "config": str(shown),
        "scenes": f"{split} training scenes",
        "steps": steps,
        "matmul_gflops": host["matmul_gflops"],
        "cpu_count": host["cpu_count"],
        "load_average": {"start": host["load_average"], "end": _load()},
        "by_vec_env": by_kind,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=8192, help="timed environment steps per arm (default 8192)")
    parser.add_argument(
        "--arms",
        nargs="+",
        default=None,
        help="forecast arms (default: none mesrnn with --json, else none cv mesrnn oracle)",
    )
    parser.add_argument(
        "--vec-env",
        nargs="+",
        default=["vector"],
        choices=VEC_ENVS,
        help="how the environments run (default vector: the batched environment); several are measured in turn",
    )
    parser.add_argument("--cells", nargs="+", default=None, help="N:KIND cells (table only; default: --vec-env kinds)")
    parser.add_argument("--split", default="zara1")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", help="config override")
    parser.add_argument("--json", action="store_true", help="one JSON object for the config's n_envs")
    args = parser.parse_args()
    extra = parse_set(args.overrides)
    arms = args.arms or (["none", "mesrnn"] if args.json else ["none", "cv", "mesrnn", "oracle"])
    arms = arms if "none" in arms else ["none", *arms]
    if args.json:
        if args.cells:
            parser.error("--json measures the config's n_envs; leave out --cells (use --set n_envs=N)")
        print(json.dumps(run_json(args.config, arms, args.vec_env, args.steps, args.split, extra)))
        return
    host = machine()
    print(
        f"{args.config.name}, split {args.split} (training scenes), {args.steps} timed steps per cell; "
        f"matmul peak {host['matmul_gflops']} GFLOP/s (float32, 1 thread), {host['cpu_count']} CPUs, "
        f"load average {host['load_average']}"
    )
    head = "".join(f"{p:>16}" for p in PHASES)
    print(
        f"{'arm':<10}{'cell':>15}{'steps/s':>10}{'slowdown':>10}{'per CPU s':>11}{'cache fill s':>14}   CPU us/step:{head}"
    )
    cells = args.cells or [f":{kind}" for kind in args.vec_env]
    for spec in cells:
        count, _, kind = spec.partition(":")
        n = int(count) if count else None
        base_rate = None
        for arm in arms:
            r = measure(args.config, arm, args.steps, args.split, extra, vec_env=kind or "dummy", n_envs=n)
            rate = r["steps_per_s"]
            base_rate = rate if arm == "none" else base_rate
            ratio = f"{base_rate / rate:.2f}x" if base_rate else "-"
            shown = f"{r['n_envs']}:{r['vec_env']}"
            parts = "".join(f"{r['cpu_split_us'][p]:>16.0f}" for p in PHASES)
            print(
                f"{arm:<10}{shown:>15}{rate:>10.0f}{ratio:>10}{r['steps_per_cpu_s']:>11.0f}{r['cache_fill_s']:>14.1f}"
                f"{parts:>15}",
                flush=True,
            )
    print(f"load average after: {_load()}")


if __name__ == "__main__":
    main()
