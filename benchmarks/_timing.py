"""Timing helper shared by the benchmark scripts (run them as ``python benchmarks/NAME.py``)."""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any


def median_seconds(fn: Callable[[], object], repeats: int, clock: Callable[[], float] = time.perf_counter) -> float:
    """Median time of ``repeats`` calls of ``fn``, in seconds: wall time, or this process's CPU time with
    ``clock=time.process_time`` (less sensitive to other processes waiting for the same cores)."""
    times = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return statistics.median(times)


def matmul_peak_gflops(dtype: Any, threads: int, repeats: int) -> float:
    """The machine's matmul peak, GFLOP/s: ``torch.mm`` of two 1024 x 1024 matrices of ``dtype`` on ``threads`` threads,
    best of ``repeats`` timings (a peak: on a shared machine the best run is the least disturbed). Printed beside a
    benchmark's figures so they can be read against the machine that produced them."""
    import torch

    torch.set_num_threads(threads)
    a, b = torch.randn(1024, 1024).to(dtype), torch.randn(1024, 1024).to(dtype)
    for _ in range(3):
        torch.mm(a, b)
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2 * 1024**3 / best / 1e9
