"""Single-process steps per second of the environment for each forecast arm, and where the time goes.

Run: ``python benchmarks/env_speed.py [--steps 3000] [--repeats 3] [--split zara1]``. A random policy
crosses the split's held-out scene (ZARA1 by default; the synthetic crowd without ETH/UCY data),
resets included. Prints the median of repeats, the ratio to the ``none`` arm measured in the same
process, and the mean microseconds per step spent in the replay, physics, forecasts, observation,
reward and resets. Cached arms are warmed first (``precompute_forecasts``; its time is printed).
Learned arms need the pretrained weights and are reported as missing otherwise. ``mesrnn carried``
uses ``forecast_memory="carried"`` (cached only: online, most resets would restart the forecaster
from the recording's first frame). Never asserts on time.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

try:  # torch is only used by the learned predictors; keep it to one thread
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    torch = None  # type: ignore[assignment]

from envs.crowd_nav import TIMING_KEYS, CrowdNavEnv
from envs.forecasts import PredictorUnavailableError

#: (label, predictor, cache, warm the cache first, forecast memory)
ARMS: tuple[tuple[str, str, bool, bool, str], ...] = (
    ("none", "none", True, False, "window"),
    ("oracle", "oracle", True, False, "window"),
    ("noisy_oracle", "noisy_oracle", True, False, "window"),
    ("cv (cached)", "cv", True, True, "window"),
    ("cv (online)", "cv", False, False, "window"),
    ("mesrnn (cached)", "mesrnn", True, True, "window"),
    ("mesrnn (online)", "mesrnn", False, False, "window"),
    ("mesrnn carried", "mesrnn", True, True, "carried"),
)


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--split", default="zara1", help="its held-out scene is replayed (default: zara1)")
    args = parser.parse_args()

    rows: list[tuple[str, float | None, dict[str, float] | None, str]] = []
    base: float | None = None
    for label, predictor, cache, warm, memory in ARMS:
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
            cached = env.precompute_forecasts()
            note += f", cache warmed: {cached} times in {time.perf_counter() - t0:.2f} s"
        results = [run(env, args.steps, seed) for seed in range(args.repeats)]
        rate = statistics.median(r[0] for r in results)
        parts = {k: statistics.median(r[1][k] for r in results) for k in (*TIMING_KEYS, "other")}
        if base is None:
            base = rate
        rows.append((label, rate, parts, note))

    keys = (*TIMING_KEYS, "other")
    print(f"CrowdNavEnv single-process speed, random policy, {args.steps} steps x {args.repeats} repeats (median)")
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
    print("\nper-part columns: mean microseconds per step; 'x none': time per step relative to the none arm")
    for label, rate, _, note in rows:
        if rate is not None:
            print(f"  {label}: {note}")


if __name__ == "__main__":
    main()
