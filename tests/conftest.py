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


def _record_line(path: str, data: bytes) -> str:
    import base64
    import hashlib

    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{path},sha256={digest},{len(data)}"


@pytest.fixture
def install_dist(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Any:
    """Install a throwaway distribution for this test only, as pip would lay it out in site-packages.

    ``install_dist(name, version, entry_points={"mine": "my_pkg:Factory"}, files={"my_pkg/__init__.py": "..."},
    record=True)`` writes ``files`` and a ``<name>-<version>.dist-info`` folder (``METADATA``, ``entry_points.txt``
    in the group ``crowdnav_mesrnn.predictors`` and, with ``record``, a ``RECORD`` of every file's SHA-256 and size as
    pip writes it; without, as an editable install's files, which its RECORD does not list) into a fresh folder put
    first on ``sys.path``, and returns that folder. The predictor registry is re-read now and after the test.
    """
    import importlib
    import sys

    from crowdnav_mesrnn import predictors
    from envs.forecasting import factory

    monkeypatch.setattr(factory, "_LOADED", {})  # predictors loaded by name before this test are forgotten
    modules: set[str] = set()

    def install(
        name: str,
        version: str = "1.0",
        entry_points: dict[str, str] | None = None,
        files: dict[str, str] | None = None,
        record: bool = True,
    ) -> Path:
        site = tmp_path_factory.mktemp(f"site-{name}")
        info = site / f"{name.replace('-', '_')}-{version}.dist-info"
        info.mkdir()
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
        lines = "".join(f"{n} = {t}\n" for n, t in (entry_points or {}).items())
        (info / "entry_points.txt").write_text(f"[{predictors.ENTRY_POINT_GROUP}]\n{lines}")
        for rel, text in (files or {}).items():
            path = site / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            modules.add(rel.split("/")[0].removesuffix(".py"))
        if record:
            listed = [*(files or {}), f"{info.name}/METADATA", f"{info.name}/entry_points.txt"]
            rows = [_record_line(rel, (site / rel).read_bytes()) for rel in listed]
            (info / "RECORD").write_text("\n".join([*rows, f"{info.name}/RECORD,,"]) + "\n")
        monkeypatch.syspath_prepend(str(site))
        forget()
        importlib.invalidate_caches()
        predictors.refresh()
        return site

    def forget() -> None:  # the packages' modules and submodules, imported from an earlier site
        for loaded in [m for m in sys.modules if m.partition(".")[0] in modules]:
            del sys.modules[loaded]

    yield install
    forget()
    monkeypatch.undo()
    importlib.invalidate_caches()
    predictors.refresh()
