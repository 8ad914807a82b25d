"""Shared fixtures. Tests needing ETH/UCY data find it exactly where the project does
(:func:`crowdnav_mesrnn.data.paths.find_data_dir`: ``$CROWDNAV_MESRNN_DATA``, ``./data/eth_ucy``,
``~/.cache/crowdnav-mesrnn/eth_ucy``) and skip only when none of those places holds it."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("SB3_LOGDIR", str(Path(__file__).resolve().parent.parent / ".pytest_cache" / "sb3"))
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
# Forecasts cached on disk by one test run are shared by its tests and processes, never read from (or written to)
# the user's cache: a run starts empty unless CROWDNAV_MESRNN_CACHE is set on purpose.
os.environ.setdefault("CROWDNAV_MESRNN_CACHE", tempfile.mkdtemp(prefix="crowdnav-mesrnn-test-cache-"))

import torch

torch.set_num_threads(1)

from crowdnav_mesrnn.data.paths import ENV_VAR, HOW_TO_GET_DATA, DataNotFoundError, candidate_dirs  # noqa: E402
from crowdnav_mesrnn.data.paths import find_data_dir as _find_data_dir  # noqa: E402


def _searched() -> str:
    """The places the project's lookup searches when no folder is given, on one line."""
    places = [f"{label} {path}" for label, path in candidate_dirs()]
    if not os.environ.get(ENV_VAR):
        places.insert(0, f"${ENV_VAR} (not set)")
    return "; ".join(places)


#: Why a test needing ETH/UCY data skips (the only reason it may): the places searched and how to get the data.
NO_DATA = f"no ETH/UCY data found (looked in: {_searched()}). {HOW_TO_GET_DATA}"


def _pin_data_dir() -> None:
    """Where the project's own lookup finds the data without the variable (``./data/eth_ucy`` or the user cache, e.g.
    after ``crowdnav-mesrnn data download``), export it as ``$CROWDNAV_MESRNN_DATA`` for this run: the tests that
    change the working directory (the docs' blocks run in a temporary one) and the subprocesses they start then use
    the same folder. A variable that is set is left as it is (set but wrong is an error, never a skip)."""
    if os.environ.get(ENV_VAR):
        return
    try:
        os.environ[ENV_VAR] = str(_find_data_dir().resolve())
    except DataNotFoundError:
        pass


_pin_data_dir()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The ETH/UCY folder the project would use; skips only when the project's lookup finds none."""
    try:
        return _find_data_dir()
    except DataNotFoundError:
        if os.environ.get(ENV_VAR):  # set but wrong is an error, not a skip: CI must not silently skip the data tests
            raise
        pytest.skip(NO_DATA)


def pytest_configure(config: pytest.Config) -> None:
    """Give SIGINT Python's default handler when the run inherited it ignored: a non-interactive shell starts
    background jobs with SIGINT ignored, and the Ctrl-C tests (like Ctrl-C in a terminal) need the default."""
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    """Every skip for missing data is reported at this fixture, so pytest's summary (``-ra``) folds them into one
    ``SKIPPED [n]`` line instead of one line per test."""
    report = yield
    longrepr = report.longrepr
    if report.skipped and isinstance(longrepr, tuple) and len(longrepr) == 3 and longrepr[2].endswith(NO_DATA):
        report.longrepr = (__file__, _DATA_DIR_LINE, longrepr[2])
    return report


#: The line of the ``data_dir`` fixture, where the folded skips are reported.
_DATA_DIR_LINE = data_dir.__wrapped__.__code__.co_firstlineno if hasattr(data_dir, "__wrapped__") else 0
