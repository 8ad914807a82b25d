"""PPO training throughput (environment steps per second, updates included) per forecast arm, and where a step goes.

Run: ``python benchmarks/train_speed.py [--json] [--steps 8192] [--arms none cv mesrnn oracle]
[--cells 8:batched 8:dummy 2:subproc] [--config configs/agent/ppo_scoring.yaml] [--split zara1] [--set key=value ...]``.

Each cell builds the PPO of the config (``agents.training``: the same policy, vectorised environment kind and networks;
validation, checkpoints and the warm start off) on the split's training scenes, with ``n_steps`` scaled so that
every update sees the config's rollout size (``n_steps x n_envs``); fills the shared forecast cache first (its time
is printed, not counted); runs one warm-up rollout; then times ``--steps`` steps of ``model.learn`` — rollouts and
updates — and splits the process's CPU time into the vectorised environment's steps (environments, observations, forecasts
lookup, action mapping), the policy's forward pass in the rollouts, the updates (``PPO.train``) and the rest
(rollout buffer, advantages, callbacks), per environment step.

A cell is a number of environments and how they run (``vec_env``): ``vector`` (the batched environment,
``agents.batched_vec_env``; ``auto`` is it where the settings allow), ``batched`` (in this process, the wrappers' work
batched: ``agents.vec_env``), ``dummy`` (SB3's ``DummyVecEnv`` over wrapped environments) or ``subproc`` (one
forkserver worker each). Without ``--cells`` the config's own (``n_envs``, ``vec_env``) is the only cell.

``--json`` prints one object: ``{"config", "split", "steps", "cell", "arms": {arm: steps/s}, "slowdown_vs_none":
{arm: none's steps/s / arm's}, "arms_per_cpu_second": {arm: steps per CPU second}, "cpu_us_per_step": {arm:
{"env", "policy_forward", "update", "other"}}}`` for the config's own cell (the shipped recipe with the default
config). Wall-time rates depend on what else the machine runs; the CPU-time rate and split do much less. Prints
figures; never asserts on time.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch

from agents.entry import parse_set
from agents.scoring import attach_geometry_cache
from agents.training.config import _algo_class, algorithm_kwargs, load_train_config, policy_class
from agents.training.run import make_vec_env, prepare_training_forecasts

torch.set_num_threads(1)

REPO = Path(__file__).resolve().parent.parent
PHASES = ("env", "policy_forward", "update", "other")


def _timed(obj: Any, name: str, totals: dict[str, float], key: str) -> None:
    """Replace ``obj.name`` by a wrapper adding its CPU time (this process's) to ``totals[key]``."""
    inner = getattr(obj, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            totals[key] += time.process_time() - t0

    setattr(obj, name, wrapper)


def cell(
    config: Path, predictor: str, n_envs: int | None, vec_env: str | None, steps: int, split: str, extra: dict
) -> tuple[float, float, float, dict[str, float]]:
    """(steps per wall second of learning, steps per CPU second of this process, seconds spent filling the forecast
    cache, CPU microseconds per step by phase) for one arm and cell (``n_envs``/``vec_env`` None: the config's
    own). On a shared machine the CPU rate is the steadier figure; with ``subproc`` workers it leaves out the
    workers' CPU (their environments)."""
    base = load_train_config(config, None, extra)
    n_envs = base.n_envs if n_envs is None else n_envs
    overrides = {
        **extra,
        "predictor": predictor,
        "split": split,
        "n_envs": n_envs,
        "vec_env": vec_env or base.vec_env,
        "n_timesteps": steps,
        "eval.episodes": 0,
        "checkpoint_freq_steps": 0,
        "pretrain": None,
    }
    if base.algo == "ppo":
        overrides["n_steps"] = max(1, int(base.hyperparams.get("n_steps", 2048)) * base.n_envs // n_envs)
    cfg = load_train_config(config, None, overrides)
    t0 = time.perf_counter()
    prepare_training_forecasts(cfg)
    cache_s = time.perf_counter() - t0
    venv = make_vec_env(cfg)
    try:
        model = _algo_class(cfg.algo)(
            policy_class(cfg.policy), venv, seed=0, verbose=0, device="cpu", **algorithm_kwargs(cfg)
        )
        attach_geometry_cache(model)
        warmup = int(cfg.hyperparams.get("n_steps", 2048)) * n_envs if cfg.algo == "ppo" else 1000
        model.learn(warmup)
        totals = dict.fromkeys(PHASES, 0.0)
        _timed(model.env, "step", totals, "env")
        _timed(model.policy, "forward", totals, "policy_forward")
        _timed(model, "train", totals, "update")
        t1, c1 = time.perf_counter(), time.process_time()
        model.learn(steps, reset_num_timesteps=False)
        elapsed, cpu = time.perf_counter() - t1, time.process_time() - c1
        totals["other"] = cpu - sum(totals.values())
        return steps / elapsed, steps / cpu, cache_s, {k: round(1e6 * v / steps, 1) for k, v in totals.items()}
    finally:
        venv.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=8192, help="timed environment steps per cell (default 8192)")
    parser.add_argument("--arms", nargs="+", default=["none", "cv", "mesrnn", "oracle"])
    parser.add_argument("--cells", nargs="+", default=None, help="N:KIND cells (default: the config's own)")
    parser.add_argument("--split", default="zara1")
    # the shipped recipe (configs/ablation/learned.yaml's PPO); configs/agent/ppo.yaml is the previous grid's
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "agent" / "ppo_scoring.yaml")
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", help="config override")
    parser.add_argument("--json", action="store_true", help="one JSON object for the config's own cell")
    args = parser.parse_args()
    extra = parse_set(args.overrides)
    arms = args.arms if "none" in args.arms else ["none", *args.arms]
    if args.json:
        if args.cells:
            parser.error("--json measures the config's own cell; leave out --cells")
        rates, cpu_rates, phases = {}, {}, {}
        for arm in arms:
            rates[arm], cpu_rates[arm], _, phases[arm] = cell(
                args.config, arm, None, None, args.steps, args.split, extra
            )
        base = load_train_config(args.config, None, extra)
        out = {
            "config": str(args.config.relative_to(REPO) if args.config.is_relative_to(REPO) else args.config),
            "split": args.split,
            "steps": args.steps,
            "cell": f"{base.n_envs}:{base.vec_env}",
            "arms": {a: round(r, 1) for a, r in rates.items()},
            "slowdown_vs_none": {a: round(rates["none"] / r, 3) for a, r in rates.items()},
            "arms_per_cpu_second": {a: round(r, 1) for a, r in cpu_rates.items()},
            "cpu_us_per_step": phases,
        }
        print(json.dumps(out))
        return
    print(f"{args.config.name}, split {args.split} (training scenes), {args.steps} timed steps per cell")
    head = "".join(f"{p:>16}" for p in PHASES)
    print(
        f"{'arm':<10}{'cell':>15}{'steps/s':>10}{'slowdown':>10}{'per CPU s':>11}{'cache fill s':>14}   CPU us/step:{head}"
    )
    for spec in args.cells or [None]:
        n, kind = (None, None) if spec is None else (int(spec.partition(":")[0]), spec.partition(":")[2] or "dummy")
        base_rate = None
        for arm in arms:
            rate, cpu_rate, cache_s, us = cell(args.config, arm, n, kind, args.steps, args.split, extra)
            base_rate = rate if arm == "none" else base_rate
            ratio = f"{base_rate / rate:.2f}x" if base_rate else "-"
            shown = spec or "config"
            parts = "".join(f"{us[p]:>16.0f}" for p in PHASES)
            print(
                f"{arm:<10}{shown:>15}{rate:>10.0f}{ratio:>10}{cpu_rate:>11.0f}{cache_s:>14.1f}{parts:>15}", flush=True
            )


if __name__ == "__main__":
    main()
