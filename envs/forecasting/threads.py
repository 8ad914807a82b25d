"""Torch threads while forecasting: one thread per computation, and fork safety.

Forecasting runs many small batched operations, where more torch threads contend for the cores rather than help:
sources compute on :func:`torch_threads` (:data:`FORECAST_THREADS`, one thread) and give the caller's setting back
after. The thread count is also part of what a forecast *is*: torch splits a reduction differently over more
threads, and a learned predictor's forecasts move in the last float32 bits (up to about 1e-5 m for MESRNN on two
threads). Every forecast that is cached or compared is therefore computed on :data:`FORECAST_THREADS`, whatever the
caller set: the environment's sources and :func:`~envs.forecasting.build.build_forecast_cache` alike. A forked child
(Gymnasium's async vector env) must not enter a torch OpenMP region its parent started (:func:`fork_safe_torch`).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Final

#: Torch threads every forecast is computed on (the documented, bit-exact setting: cached files, online forecasts
#: and ``forecasts build`` give the same bits).
FORECAST_THREADS: Final[int] = 1
#: The process that imported this module; a process with another id is a forked child (or a child's child).
_IMPORT_PID: Final[int] = os.getpid()
#: The forked process that has already been switched to one torch thread.
_ONE_THREAD_PID: int | None = None


def fork_safe_torch() -> None:
    """In a forked child, run torch on one thread from here on; elsewhere nothing.

    A forked process inherits the parent's GNU OpenMP (``libgomp``) state but not its worker threads: once the
    parent has run a parallel torch operation (loading or hashing a predictor, a user's own torch code), the child's
    first parallel operation waits forever for threads that do not exist. Gymnasium's async vector env forks its
    workers, which build their environments and compute forecasts when the cache is cold; every path that runs a
    predictor (:func:`~envs.forecasting.factory.make_forecast_source`, the chunks and frames of
    :class:`~envs.forecasting.window.PredictorForecast`) calls this first, so torch never enters an OpenMP region
    there. A worker of vectorised environments needs one thread anyway; processes started with ``spawn`` or
    ``forkserver`` import this module afresh and keep their threads. (A fork is recognised by the process id, not by an
    ``os.register_at_fork`` hook: a hook would keep ``sys.modules`` alive into interpreter shutdown, where pymunk's
    spaces must not be freed.)
    """
    global _ONE_THREAD_PID
    pid = os.getpid()
    if pid == _IMPORT_PID or pid == _ONE_THREAD_PID:
        return
    torch = sys.modules.get("torch")
    if torch is not None:  # not imported: the parent had no torch state to inherit
        torch.set_num_threads(1)
    _ONE_THREAD_PID = pid


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run torch on ``n`` threads inside the block and restore the caller's count after (nothing without torch, or
    with ``n`` None)."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None and n is not None else n
    if before == n:
        yield
        return
    torch.set_num_threads(n)  # type: ignore[union-attr]
    try:
        yield
    finally:
        torch.set_num_threads(before)  # type: ignore[union-attr]
