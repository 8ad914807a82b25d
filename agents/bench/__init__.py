"""``crowdnav-mesrnn bench PREDICTOR``: the project's navigation answer for any predictor, on one page.

Two halves, each resumable and cached under ``--out``:

1. :mod:`agents.bench.metrics` — ADE/FDE on the ETH/UCY leave-one-out test windows against constant velocity
   (paired, block-bootstrap intervals);
2. :mod:`agents.bench.planner` — the sampling planner on the held-out scenes with the predictor's forecasts,
   against cv, the oracle and the noisy-oracle sweep on the same episodes (exact McNemar, Holm).

:mod:`agents.bench.report` writes ``report.md``, ``report.json`` and ``success_vs_ade.png``. The planner cells run
on the ablation's grid machinery (:mod:`agents.ablation`: a local process pool, or Ray with ``--backend ray``).

The code is in modules: :mod:`agents.bench.run` (:func:`run_bench`, :class:`BenchConfig`) and
:mod:`agents.bench.cli` (the command line, :func:`add_parser` named by ``crowdnav-mesrnn``).
"""

from __future__ import annotations

from typing import Any

from agents.bench.cli import add_parser, main

__all__ = ["BenchConfig", "add_parser", "default_out", "main", "run_bench"]


def __getattr__(name: str) -> Any:
    if name in ("BenchConfig", "default_out", "run_bench"):  # torch comes with them, not with the command line
        from agents.bench import run

        return getattr(run, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
