"""Where a step's time goes: wall time per named phase, exclusive of nested phases.

A method decorated with :func:`timed` adds its duration to ``self._timer.totals[key]``, minus the time spent
in timed methods it calls, so the phases of a step add up without double counting and the step itself
stays free of bookkeeping.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from time import perf_counter
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])


class PhaseTimer:
    """Accumulated seconds per phase key (``totals``), exclusive of nested phases."""

    def __init__(self, keys: tuple[str, ...]) -> None:
        self.keys = keys
        self.totals: dict[str, float] = dict.fromkeys(keys, 0.0)
        self.nested: list[float] = []

    def reset(self) -> None:
        self.totals = dict.fromkeys(self.keys, 0.0)
        self.nested = []


def timed(key: str) -> Callable[[F], F]:
    """Decorate a method of an object with a ``_timer`` (:class:`PhaseTimer`) so its time counts under ``key``."""

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def phase(self: Any, *args: Any, **kwargs: Any) -> Any:
            timer: PhaseTimer = self._timer
            timer.nested.append(0.0)
            start = perf_counter()
            try:
                return fn(self, *args, **kwargs)
            finally:
                elapsed = perf_counter() - start
                timer.totals[key] += elapsed - timer.nested.pop()
                if timer.nested:
                    timer.nested[-1] += elapsed

        return phase  # type: ignore[return-value]

    return wrap
