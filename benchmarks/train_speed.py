"""PPO training throughput (environment steps per second, updates included) per forecast arm, 1 and 2 envs.

Run: ``python benchmarks/train_speed.py [--steps 8192] [--arms none cv mesrnn oracle]
[--cells 1:dummy 2:subproc 2:dummy 8:dummy] [--config configs/agent/ppo.yaml] [--set key=value ...]``.
A cell is a number of environments and how they run: ``dummy`` (stepped in lockstep in the training
process) or ``subproc`` (one forkserver worker process each). Each cell builds the PPO of the config
(``agents.train``: the same extractor and networks; validation and checkpoints off) on the split's
training scenes, with ``n_steps`` scaled so that every update sees the config's rollout size
(``n_steps x n_envs``); fills the shared forecast cache first (its time is printed, not counted); runs
one warm-up rollout; then times ``--steps`` steps of ``model.learn`` — rollouts and updates — and prints
steps/s and the slowdown against the ``none`` arm of the same cell. Prints figures; never asserts on time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from agents.evaluate import parse_set, prepare_forecasts
from agents.train import _algo_class, algorithm_kwargs, load_train_config, make_vec_env, policy_class

torch.set_num_threads(1)

REPO = Path(__file__).resolve().parent.parent


def cell(
    config: Path, predictor: str, n_envs: int, vec_env: str, steps: int, split: str, extra: dict
) -> tuple[float, float]:
    """(steps/s of learning, seconds spent filling the forecast cache) for one arm and cell."""
    base = load_train_config(config, None, extra)
    overrides = {
        **extra,
        "predictor": predictor,
        "split": split,
        "n_envs": n_envs,
        "vec_env": vec_env,
        "n_timesteps": steps,
        "eval.episodes": 0,
        "checkpoint_freq_steps": 0,
        "pretrain": None,
    }
    if base.algo == "ppo":
        overrides["n_steps"] = max(1, int(base.hyperparams.get("n_steps", 2048)) * base.n_envs // n_envs)
    cfg = load_train_config(config, None, overrides)
    t0 = time.perf_counter()
    prepare_forecasts(cfg.env_kwargs("train"), progress=False)
    cache_s = time.perf_counter() - t0
    venv = make_vec_env(cfg)
    try:
        model = _algo_class(cfg.algo)(
            policy_class(cfg.policy), venv, seed=0, verbose=0, device="cpu", **algorithm_kwargs(cfg)
        )
        warmup = int(cfg.hyperparams.get("n_steps", 2048)) * n_envs if cfg.algo == "ppo" else 1000
        model.learn(warmup)
        t1 = time.perf_counter()
        model.learn(steps, reset_num_timesteps=False)
        return steps / (time.perf_counter() - t1), cache_s
    finally:
        venv.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=8192, help="timed environment steps per cell (default 8192)")
    parser.add_argument("--arms", nargs="+", default=["none", "cv", "mesrnn", "oracle"])
    parser.add_argument("--cells", nargs="+", default=["1:dummy", "2:subproc", "2:dummy", "8:dummy"])
    parser.add_argument("--split", default="zara1")
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "agent" / "ppo.yaml")
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", help="config override")
    args = parser.parse_args()
    extra = parse_set(args.overrides)
    arms = args.arms if "none" in args.arms else ["none", *args.arms]
    print(f"{args.config.name}, split {args.split} (training scenes), {args.steps} timed steps per cell")
    print(f"{'arm':<10}{'envs':>6}{'vec_env':>9}{'steps/s':>10}{'slowdown':>10}{'cache fill s':>14}")
    for spec in args.cells:
        n, _, vec_env = spec.partition(":")
        base = None
        for arm in arms:
            rate, cache_s = cell(args.config, arm, int(n), vec_env or "dummy", args.steps, args.split, extra)
            base = rate if arm == "none" else base
            ratio = f"{base / rate:.2f}x" if base else "-"
            print(f"{arm:<10}{n:>6}{vec_env:>9}{rate:>10.0f}{ratio:>10}{cache_s:>14.1f}", flush=True)


if __name__ == "__main__":
    main()
