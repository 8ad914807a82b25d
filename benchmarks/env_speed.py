"""Steps per second of the environment for each forecast arm: batched, in one process, in a fresh process, and under
PPO.

Run: ``python benchmarks/env_speed.py [--batched-steps 4000] [--steps 3000] [--repeats 3] [--split zara1]
[--fresh-steps 1500] [--ppo-steps 0] [--reaction]``. Up to five parts, each printing medians of repeats and ratios
against a reference measured the same way (the single environment, the ``none`` arm, or ``reaction="none"``):

0. **Batched** (``--batched-steps``, 0 skips it): the batched environment (:class:`envs.vector.BatchedCrowdNavEnv`)
   at N = 1, 16 and 64 worlds against the single environment and ``SyncVectorEnv`` over N single environments, for
   the ``none`` and ``mesrnn`` arms on the split's held-out scene, a random policy, autoresets included; steps/s
   by CPU time of the process (robust to a shared machine) and by wall time, the ratio to the single environment
   measured in the same repeat, the machine's matmul peak beside, and the batched environment's split per phase
   at the largest N. MESRNN forecasts come from the disk cache, which is built first for the held-out scene's
   recording when missing (what was loaded or computed is printed).

1. **In one process**: a random policy crosses the split's held-out scene (ZARA1 by default; the synthetic crowd
   without ETH/UCY data), resets included, with the mean microseconds per step spent in the replay, physics,
   forecasts, observation, reward and resets. Cached arms load (or first build) their forecasts
   (``precompute_forecasts``; its time is printed). ``mesrnn (online)`` computes every forecast when needed
   (no cache; run for a tenth of the steps).
2. **Fresh process**: ``gymnasium.make(id)`` with the default configuration in a new interpreter, stepping a
   random policy from its first step (``--fresh-steps``), for ``CrowdNav-NoPred-v0`` and ``CrowdNav-MESRNN-v0``
   alternately, after the MESRNN forecasts of the split are on disk (``build_forecast_cache``). Steps/s by CPU
   time of the process (robust to a shared machine) and by wall time; the time to make the env is printed apart.
3. **PPO** (``--ppo-steps N``, off by default): Stable-Baselines3 PPO (``MultiInputPolicy``, ``n_steps=512``) on
   2 ``SubprocVecEnv`` workers of the default configuration, ``none`` against ``mesrnn`` (cache on disk), wall
   time of ``learn(N)``; ``cv`` as a control with MESRNN's observation (so the same policy network) and cheap
   forecasts: what ``mesrnn`` costs beyond ``cv`` is its forecasts, what ``cv`` costs beyond ``none`` is the
   larger observation.
4. **Reaction models** (``--reaction``; ``--reaction-only`` skips the others): env steps/s of each ``reaction``
   against ``reaction="none"`` in one process, for each arm of ``--reaction-arms`` (default ``cv oracle mesrnn``) on
   the held-out scene of ``--reaction-split`` (default univ: the densest crowds), by the process's CPU time (median of
   ``--repeats``), with cached forecasts for the unreacted (a learned arm runs only when its forecasts of the scene
   are on disk: building them takes minutes, ``crowdnav-mesrnn forecasts build``). The rows of an arm and robot are
   measured in turns (repeat ``k`` of every row, seed ``k``, before repeat ``k + 1`` of any), and ``x none`` is the
   median over repeats of each repeat's ratio to ``none``'s, so a load that changes while the part runs (a shared
   machine) moves a row and its reference alike. Two robots: a random policy (as
   part 1) and a robot standing where it starts (people walk up to it: the most reacting). Each row also gives the
   microseconds per step spent in the reaction model and in forecasts, and the frames forecast from observed
   histories (those with a reacted pedestrian in their window: the learned arms' extra cost). The rows ``control
   step`` step the model once per control step instead of every physics substep (the alternative the environment
   does not use: see :mod:`envs.reactive`). The machine's single-thread fp32 matmul peak is printed beside.

The forecast cache is the usual one (``$CROWDNAV_MESRNN_CACHE`` or ``~/.cache/crowdnav-mesrnn/forecasts``).
Learned arms need the pretrained weights and are reported as missing otherwise. Never asserts on time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

try:  # torch is only used by the learned predictors; keep it to one thread
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    torch = None  # type: ignore[assignment]

from _timing import matmul_peak_gflops

from envs.crowd_nav import TIMING_KEYS, CrowdNavEnv
from envs.forecasting.build import build_forecast_cache
from envs.forecasting.cache import num_chunks
from envs.forecasting.factory import PredictorUnavailableError
from envs.forecasting.window import PredictorForecast

#: (label, predictor, cache, warm the cache first, forecast memory, share of --steps)
ARMS: tuple[tuple[str, str, bool, bool, str, float], ...] = (
    ("none", "none", True, False, "window", 1.0),
    ("oracle", "oracle", True, False, "window", 1.0),
    ("noisy_oracle", "noisy_oracle", True, False, "window", 1.0),
    ("cv (cached)", "cv", True, True, "window", 1.0),
    ("cv (online)", "cv", False, False, "window", 1.0),
    ("mesrnn (cached)", "mesrnn", True, True, "window", 1.0),
    ("mesrnn (online)", "mesrnn", False, False, "window", 0.1),
    ("mesrnn carried", "mesrnn", True, True, "carried", 1.0),
)

#: Rows of part 4: (label, reaction, stepping of the model; None: the environment's).
REACTION_ROWS: tuple[tuple[str, str, str | None], ...] = (
    ("none", "none", None),
    ("pause", "pause", None),
    ("orca", "orca", None),
    ("social_force", "social_force", None),
    ("orca, control step", "orca", "control"),
    ("social_force, control step", "social_force", "control"),
)

FRESH = """
import sys, time, json
wall0, cpu0 = time.perf_counter(), time.process_time()
import numpy as np, torch
torch.set_num_threads(1)
import gymnasium, crowdnav_mesrnn
env = gymnasium.make(sys.argv[1])
made = time.perf_counter() - wall0
actions = np.random.default_rng(0).uniform(-1, 1, (int(sys.argv[2]), 2)).astype(np.float32)
env.reset(seed=0)
wall, cpu = time.perf_counter(), time.process_time()
for a in actions:
    _, _, terminated, truncated, _ = env.step(a)
    if terminated or truncated:
        env.reset()
wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
f = env.unwrapped.forecaster
print(json.dumps({"cpu": len(actions) / cpu, "wall": len(actions) / wall, "make_s": made,
                  "computed": getattr(f, "calls", 0)}))
"""

PPO = """
import sys, time, json
import torch
torch.set_num_threads(1)
import gymnasium, crowdnav_mesrnn
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import SubprocVecEnv

def main():
    vec = make_vec_env(sys.argv[1], n_envs=2, seed=0, vec_env_cls=SubprocVecEnv)
    model = PPO("MultiInputPolicy", vec, n_steps=512, batch_size=256, seed=0, verbose=0, device="cpu")
    start = time.perf_counter()
    model.learn(int(sys.argv[2]))
    print(json.dumps({"steps_per_s": int(sys.argv[2]) / (time.perf_counter() - start)}))
    vec.close()

if __name__ == "__main__":
    main()
"""


def run(
    env: CrowdNavEnv, steps: int, seed: int, clock: Any = time.perf_counter, standing: bool = False
) -> tuple[float, dict[str, float], int, tuple[int, int]]:
    """Steps per second of ``clock`` (wall time, or ``time.process_time``: this process's CPU time) over ``steps``
    random steps (zero actions with ``standing``), resets included; the mean seconds per step of each timed part
    (``other``: the rest of the step); the frames forecast meanwhile; and (episodes ended by a collision, episodes
    ended)."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, size=(steps, 2)).astype(np.float32)
    if standing:
        actions[:] = 0.0
    env.reset(seed=seed)
    env.reset_timings()
    calls = getattr(env.forecaster, "calls", 0)
    ended = collided = 0
    start = clock()
    for a in actions:
        _, _, terminated, truncated, info = env.step(a)
        if terminated or truncated:
            ended += 1
            collided += info["episode_metrics"]["outcome"] == "collision"
            env.reset()
    elapsed = clock() - start
    parts = {k: v / steps for k, v in env.timings.items()}
    parts["other"] = elapsed / steps - sum(parts.values())
    return steps / elapsed, parts, getattr(env.forecaster, "calls", 0) - calls, (collided, ended)


def _rate(step: Any, steps: int) -> tuple[float, float]:
    """``(world-steps per CPU second, per wall second)`` of ``step()`` called ``steps`` times (it returns the number of
    world-steps it took)."""
    wall, cpu = time.perf_counter(), time.process_time()
    done = sum(step() for _ in range(steps))
    return done / (time.process_time() - cpu), done / (time.perf_counter() - wall)


def _single_stepper(env: CrowdNavEnv, rng: np.random.Generator) -> Any:
    env.reset(seed=0)

    def step() -> int:
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1.0, 1.0, 2).astype(np.float32))
        if terminated or truncated:
            env.reset()
        return 1

    return step


def _vector_stepper(envs: Any, rng: np.random.Generator) -> Any:
    envs.reset(seed=0)
    n = envs.num_envs

    def step() -> int:
        envs.step(rng.uniform(-1.0, 1.0, (n, 2)).astype(np.float32))
        return n

    return step


def batched(args: argparse.Namespace) -> None:
    from gymnasium.vector import SyncVectorEnv

    from envs.vector import BatchedCrowdNavEnv

    sizes = (1, 16, 64)
    peak = float("nan")
    if torch is not None:
        peak = matmul_peak_gflops(torch.float32, 1, 5)
        torch.set_num_threads(1)
    print(
        f"0. Batched environment, {args.split} held-out scene, random policy, {args.batched_steps} world-steps per "
        f"measurement x {args.repeats} repeats (median); machine: {os.cpu_count()} CPUs, 1-thread fp32 matmul peak "
        f"{peak:.0f} GFLOP/s, load average {_load()} (other processes)"
    )
    try:
        summary = build_forecast_cache("mesrnn", args.split, "test", progress=False)
        print(
            f"   MESRNN forecasts of {', '.join(summary['recordings'])}: {summary['chunks']} chunks on disk, "
            f"{summary['loaded']} loaded, {summary['computed']} computed now ({summary['seconds']:.1f} s)"
        )
        arms = ("none", "mesrnn")
    except PredictorUnavailableError as exc:
        print(f"   mesrnn skipped: {str(exc).split('. ')[0]}")
        arms = ("none",)
    header = (
        f"{'arm':<8}{'environment':<16}{'N':>4}{'steps/s cpu':>13}{'x single':>10}{'steps/s wall':>14}{'x single':>10}"
    )
    print(header)
    print("-" * len(header))
    for arm in arms:
        kwargs = {"predictor": arm, "split": args.split, "part": "test"}
        rng = np.random.default_rng(0)
        single = CrowdNavEnv(**kwargs)
        single.precompute_forecasts()
        runs: dict[tuple[str, int], Any] = {("single", 1): _single_stepper(single, rng)}
        for n in sizes[1:]:
            runs[("SyncVectorEnv", n)] = _vector_stepper(SyncVectorEnv([partial(CrowdNavEnv, **kwargs)] * n), rng)
        envs = {n: BatchedCrowdNavEnv(num_envs=n, **kwargs) for n in sizes}
        for n, env in envs.items():
            runs[("batched", n)] = _vector_stepper(env, rng)
        rates: dict[tuple[str, int], list[tuple[float, float]]] = {key: [] for key in runs}
        for _ in range(args.repeats):  # interleaved, so every repeat sees the same machine load
            for key, step in runs.items():
                rates[key].append(_rate(step, max(1, args.batched_steps // key[1])))
        base = rates[("single", 1)]
        for key in runs:
            cpu = statistics.median(r[0] for r in rates[key])
            wall = statistics.median(r[1] for r in rates[key])
            x_cpu = statistics.median(r[0] / b[0] for r, b in zip(rates[key], base, strict=True))
            x_wall = statistics.median(r[1] / b[1] for r, b in zip(rates[key], base, strict=True))
            print(f"{arm:<8}{key[0]:<16}{key[1]:>4}{cpu:>13.0f}{x_cpu:>10.2f}{wall:>14.0f}{x_wall:>10.2f}")
        big = envs[sizes[-1]]
        step = _vector_stepper(big, rng)
        big.reset_timings()
        wall0 = time.perf_counter()
        done = sum(step() for _ in range(max(1, args.batched_steps // sizes[-1])))
        total = (time.perf_counter() - wall0) / done
        split = {k: v / done for k, v in big.timings.items() if v > 0}  # (never "reaction": none is batched)
        split["other"] = total - sum(split.values())
        print(
            f"   batched N={sizes[-1]} ({arm}), wall microseconds per world-step by phase: "
            + ", ".join(f"{k} {1e6 * v:.1f}" for k, v in split.items())
            + f"; total {1e6 * total:.1f}"
        )
    print("   'x single': steps/s relative to the single environment in the same repeat (median of the ratios)")
    print(f"   load average at the end: {_load()}\n")


def _load() -> str:
    """The 1-minute load average (processes running or waiting for a CPU), or ``n/a``."""
    try:
        return f"{os.getloadavg()[0]:.1f}"
    except OSError:
        return "n/a"


def in_process(args: argparse.Namespace) -> None:
    rows: list[tuple[str, float | None, dict[str, float] | None, str]] = []
    base: float | None = None
    for label, predictor, cache, warm, memory, share in ARMS:
        try:
            env = CrowdNavEnv(
                predictor=predictor, split=args.split, part="test", cache_forecasts=cache, forecast_memory=memory
            )
        except PredictorUnavailableError as exc:
            rows.append((label, None, None, f"skipped: {str(exc).split('. ')[0]}"))
            continue
        note = f"{env.recordings[0].name} ({env.crowd_kind})"
        if warm:
            t0 = time.perf_counter()
            frames = env.precompute_forecasts()
            note += f", forecasts at {frames} frames loaded or built in {time.perf_counter() - t0:.2f} s"
        steps = max(100, int(args.steps * share))
        results = [run(env, steps, seed) for seed in range(args.repeats)]
        rate = statistics.median(r[0] for r in results)
        parts = {k: statistics.median(r[1][k] for r in results) for k in (*TIMING_KEYS, "other")}
        if base is None:
            base = rate
        rows.append((label, rate, parts, note + ("" if share == 1.0 else f", {steps} steps")))

    keys = (*TIMING_KEYS, "other")
    print(f"1. One process, random policy, {args.steps} steps x {args.repeats} repeats (median)")
    header = f"{'arm':<17}{'steps/s':>9}{'x none':>8}{'us/step':>9}  " + "".join(f"{k:>12}" for k in keys)
    print(header)
    print("-" * len(header))
    for label, rate, parts, note in rows:
        if rate is None or parts is None:
            print(f"{label:<17}{'-':>9}{'-':>8}{'-':>9}  {note}")
            continue
        slower = (base / rate) if base else float("nan")
        line = f"{label:<17}{rate:>9.0f}{slower:>8.2f}{1e6 / rate:>9.0f}  " + "".join(
            f"{1e6 * parts[k]:>12.1f}" for k in keys
        )
        print(line)
    print("per-part columns: mean microseconds per step; 'x none': time per step relative to the none arm")
    for label, rate, _, note in rows:
        if rate is not None:
            print(f"  {label}: {note}")


def _child(code: str, *argv: str) -> dict[str, float]:
    """Run ``code`` as a script in a new interpreter (a file: SubprocVecEnv's workers re-import the main module)."""
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "child.py"
        script.write_text(code)
        out = subprocess.run([sys.executable, str(script), *argv], capture_output=True, text=True, cwd=tmp)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark child failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def fresh_process(args: argparse.Namespace) -> None:
    summary = build_forecast_cache("mesrnn", "zara1", "all", progress=False)
    print(
        f"\n2. Fresh process, default configuration (zara1 train), random policy, {args.fresh_steps} steps from the "
        f"first, {args.repeats} alternating repeats (median); MESRNN forecasts on disk "
        f"({summary['chunks']} chunks, {summary['computed']} computed now, {summary['seconds']:.1f} s)"
    )
    ids = ("CrowdNav-NoPred-v0", "CrowdNav-MESRNN-v0")
    runs: dict[str, list[dict[str, float]]] = {i: [] for i in ids}
    for _ in range(args.repeats):
        for env_id in ids:
            runs[env_id].append(_child(FRESH, env_id, str(args.fresh_steps)))
    med = {i: {k: statistics.median(r[k] for r in runs[i]) for k in runs[i][0]} for i in ids}
    print(f"{'id':<22}{'steps/s (cpu)':>15}{'x NoPred':>10}{'steps/s (wall)':>16}{'x NoPred':>10}{'make s':>8}")
    for env_id in ids:
        m, b = med[env_id], med[ids[0]]
        print(
            f"{env_id:<22}{m['cpu']:>15.0f}{b['cpu'] / m['cpu']:>10.2f}{m['wall']:>16.0f}{b['wall'] / m['wall']:>10.2f}"
            f"{m['make_s']:>8.2f}"
        )
    print(f"  frames forecast by the MESRNN processes (0 = everything loaded): {[r['computed'] for r in runs[ids[1]]]}")


def ppo(args: argparse.Namespace) -> None:
    build_forecast_cache("mesrnn", "zara1", "all", progress=False)
    print(
        f"\n3. SB3 PPO, 2 SubprocVecEnv workers, n_steps=512, learn({args.ppo_steps}), {args.repeats} repeats (median)"
    )
    # CV: the same observation (and policy network) as MESRNN, forecasts computed in memory from the data
    ids = ("CrowdNav-NoPred-v0", "CrowdNav-MESRNN-v0", "CrowdNav-CV-v0")
    rates: dict[str, list[float]] = {i: [] for i in ids}
    for _ in range(args.repeats):
        for env_id in ids:
            rates[env_id].append(_child(PPO, env_id, str(args.ppo_steps))["steps_per_s"])
    base = statistics.median(rates[ids[0]])
    for env_id in ids:
        rate = statistics.median(rates[env_id])
        print(
            f"{env_id:<22}{rate:>9.0f} steps/s{base / rate:>8.2f} x NoPred   runs: {[round(r) for r in rates[env_id]]}"
        )


def on_disk(env: CrowdNavEnv) -> bool:
    """Every forecast chunk of the env's recordings is in the disk cache (True for sources without one)."""
    source = env.forecaster
    if not isinstance(source, PredictorForecast) or source.store is None:
        return True
    for rec in env.recordings:
        key = source.table_key(rec)
        if key is None:
            return True
        if any(source.store.load(key, c, rec, quiet=True) is None for c in range(num_chunks(rec))):
            return False
    return True


def reactions(args: argparse.Namespace) -> None:
    peak = matmul_peak_gflops(torch.float32, 1, 9) if torch is not None else float("nan")
    print(
        f"\n4. Reaction models: {args.reaction_split} held-out scene, {args.reaction_steps} steps x {args.repeats} "
        f"repeats (median), steps per CPU second of this process; machine: fp32 matmul peak {peak:.0f} GFLOP/s on 1 "
        "thread"
    )
    header = (
        f"{'arm':<8}{'robot':<10}{'reaction':<28}{'steps/s':>9}{'x none':>8}{'reaction us':>13}{'forecasts us':>14}"
        f"{'online frames':>15}{'collisions':>12}"
    )
    print(header, flush=True)
    print("-" * len(header))
    for arm in args.reaction_arms:
        try:
            probe = CrowdNavEnv(predictor=arm, split=args.reaction_split, part="test")
        except PredictorUnavailableError as exc:
            print(f"{arm:<8}skipped: {str(exc).split('. ')[0]}")
            continue
        if not on_disk(probe):
            print(
                f"{arm:<8}skipped: its forecasts of {', '.join(r.name for r in probe.recordings)} are not on disk "
                f"(crowdnav-mesrnn forecasts build --predictor {arm} --split {args.reaction_split} --part test)"
            )
            continue
        envs = []
        for _, reaction, stepping in REACTION_ROWS:
            env = CrowdNavEnv(predictor=arm, split=args.reaction_split, part="test", reaction=reaction)
            if stepping is not None:
                env._reactive.stepping = stepping  # a benchmark of the alternative: not a configuration key
            env.precompute_forecasts()
            envs.append(env)
        for standing in (False, True):
            runs: list[list[Any]] = [[] for _ in REACTION_ROWS]
            for seed in range(args.repeats):  # in turns: repeat k of every row, then repeat k + 1
                for row, env in zip(runs, envs, strict=True):
                    row.append(run(env, args.reaction_steps, seed, time.process_time, standing))
            for (label, _, _), row in zip(REACTION_ROWS, runs, strict=True):
                rate = statistics.median(r[0] for r in row)
                ratio = statistics.median(b[0] / r[0] for b, r in zip(runs[0], row, strict=True))
                parts = {k: statistics.median(r[1][k] for r in row) for k in ("reaction", "forecasts")}
                online = statistics.median(r[2] for r in row)
                collided, ended = (sum(r[3][i] for r in row) for i in (0, 1))
                print(
                    f"{arm:<8}{'standing' if standing else 'random':<10}{label:<28}{rate:>9.0f}{ratio:>8.2f}"
                    f"{1e6 * parts['reaction']:>13.0f}{1e6 * parts['forecasts']:>14.0f}{online:>15.0f}"
                    f"{f'{collided}/{ended}':>12}",
                    flush=True,
                )
    print(
        "x none: CPU time per step relative to reaction none (same arm and robot; median over repeats of the ratio "
        "within each repeat); reaction/forecasts us: wall "
        "microseconds per step in the model and in forecasts; online frames: frames forecast from observed histories "
        "per run (cv: per pedestrian, cheap; a learned arm: the whole scene, one predictor call each); collisions: "
        "episodes ended by a collision / episodes ended, over the repeats"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--split", default="zara1", help="its held-out scene is replayed in part 1 (default: zara1)")
    parser.add_argument("--fresh-steps", type=int, default=1500, help="steps per fresh process (0: skip part 2)")
    parser.add_argument("--ppo-steps", type=int, default=0, help="PPO steps per arm (default 0: skip part 3)")
    parser.add_argument("--skip-in-process", action="store_true", help="skip part 1")
    parser.add_argument("--batched-steps", type=int, default=4000, help="world-steps per batched measurement (0: skip)")
    parser.add_argument("--reaction", action="store_true", help="part 4: env steps/s per reaction model")
    parser.add_argument("--reaction-only", action="store_true", help="only part 4")
    parser.add_argument("--reaction-split", default="univ", help="its held-out scene is replayed in part 4")
    parser.add_argument("--reaction-arms", nargs="+", default=["cv", "oracle", "mesrnn"], help="arms of part 4")
    parser.add_argument("--reaction-steps", type=int, default=1500, help="steps per run of part 4")
    args = parser.parse_args()
    if args.reaction_only:
        reactions(args)
        return
    if args.batched_steps:
        batched(args)
    if not args.skip_in_process:
        in_process(args)
    if args.fresh_steps:
        fresh_process(args)
    if args.ppo_steps:
        ppo(args)
    if args.reaction:
        reactions(args)


if __name__ == "__main__":
    main()
