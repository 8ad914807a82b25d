"""Steps per second of the environment for each forecast arm: in one process, in a fresh process, and under PPO.

Run: ``python benchmarks/env_speed.py [--steps 3000] [--repeats 3] [--split zara1] [--fresh-steps 1500]
[--ppo-steps 0]``. Three parts, each printing medians of repeats and ratios against the ``none`` arm measured
the same way:

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

The forecast cache is the usual one (``$CROWDNAV_MESRNN_CACHE`` or ``~/.cache/crowdnav-mesrnn/forecasts``).
Learned arms need the pretrained weights and are reported as missing otherwise. Never asserts on time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

try:  # torch is only used by the learned predictors; keep it to one thread
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    torch = None  # type: ignore[assignment]

from envs.crowd_nav import TIMING_KEYS, CrowdNavEnv
from envs.forecasting.build import build_forecast_cache
from envs.forecasting.factory import PredictorUnavailableError

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


def run(env: CrowdNavEnv, steps: int, seed: int) -> tuple[float, dict[str, float]]:
    """Steps per second over ``steps`` random steps, and mean seconds per step of each timed part."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, size=(steps, 2)).astype(np.float32)
    env.reset(seed=seed)
    env.reset_timings()
    start = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    parts = {k: v / steps for k, v in env.timings.items()}
    parts["other"] = elapsed / steps - sum(parts.values())
    return steps / elapsed, parts


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--split", default="zara1", help="its held-out scene is replayed in part 1 (default: zara1)")
    parser.add_argument("--fresh-steps", type=int, default=1500, help="steps per fresh process (0: skip part 2)")
    parser.add_argument("--ppo-steps", type=int, default=0, help="PPO steps per arm (default 0: skip part 3)")
    parser.add_argument("--skip-in-process", action="store_true", help="skip part 1")
    args = parser.parse_args()
    if not args.skip_in_process:
        in_process(args)
    if args.fresh_steps:
        fresh_process(args)
    if args.ppo_steps:
        ppo(args)


if __name__ == "__main__":
    main()
