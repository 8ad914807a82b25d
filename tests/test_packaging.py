"""The wheel holds every package of the project and its data (issue 27 item 10): a non-editable install had no
``crowdnav-mesrnn bench`` when ``agents.bench`` was missing from an explicit package list. CI also installs the wheel
in a fresh virtual environment and runs the CLI from outside the checkout (``.ci/run``)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The project's top-level packages (pyproject.toml's package discovery).
PACKAGES = ("crowdnav_mesrnn", "envs", "agents")

#: building the wheel takes a while: the whole module runs in CI (`-m "slow or not slow"`)
pytestmark = pytest.mark.slow


def _setuptools_major() -> int:
    try:
        from importlib.metadata import version

        return int(version("setuptools").split(".")[0])
    except Exception:  # not installed, or an odd version string
        return 0


def expected_files() -> set[str]:
    """What the wheel must hold: every module of the three packages, ``py.typed`` and every file of a
    ``pretrained`` folder (weights, cv_gaussian parameters, the shipped policy) but its README."""
    out = set()
    for top in PACKAGES:
        for path in (REPO / top).rglob("*"):
            rel = path.relative_to(REPO)
            if not path.is_file() or "__pycache__" in rel.parts:
                continue
            if path.suffix == ".py" or path.name == "py.typed" or ("pretrained" in rel.parts and path.suffix != ".md"):
                out.add(rel.as_posix())
    return out


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A wheel built (``pip wheel --no-deps``) from a copy of the checkout, so the build's own folders (``build/``,
    ``*.egg-info``) land neither in the checkout nor in the wheel."""
    if _setuptools_major() < 77:
        why = "building the wheel here needs setuptools>=77 (pip install -e '.[dev]')"
        pytest.fail(f"CI installs the dev extra: {why}") if os.environ.get("CI") else pytest.skip(why)
    src = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, src / name)
    for top in PACKAGES:
        shutil.copytree(REPO / top, src / top, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("wheel")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(src)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    [built] = out.glob("crowdnav_mesrnn-*.whl")
    return built


@pytest.fixture(scope="module")
def wheel_files(wheel: Path) -> set[str]:
    with zipfile.ZipFile(wheel) as zf:
        return set(zf.namelist())


def test_every_package_folder_with_modules_is_in_the_wheel(wheel_files: set[str]) -> None:
    folders = {str(Path(f).parent) for f in expected_files() if f.endswith(".py")}
    assert {"agents/bench", "agents/ablation", "envs/forecasting", "envs/reaction", "crowdnav_mesrnn/cli"} <= folders
    missing = sorted(d for d in folders if f"{d}/__init__.py" not in wheel_files)
    assert not missing, f"package folders missing from the wheel: {missing}"


def test_every_module_and_data_file_is_in_the_wheel(wheel_files: set[str]) -> None:
    expected = expected_files()
    assert "agents/pretrained/ppo_mesrnn_zara1.policy.yaml" in expected
    assert "agents/pretrained/ppo_mesrnn_zara1.pt" in expected
    assert "crowdnav_mesrnn/pretrained/cv_gaussian_zara1.json" in expected
    assert "crowdnav_mesrnn/pretrained/mesrnn_zara1.pt" in expected
    assert sorted(expected - wheel_files) == []
    # and nothing of the checkout that is not the project's (tests, build folders)
    assert not [f for f in wheel_files if f.split("/")[0] in ("tests", "build", "docs", "examples")]


def test_the_wheel_declares_the_console_script_and_the_shipped_predictors(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as zf:
        [name] = [f for f in zf.namelist() if f.endswith(".dist-info/entry_points.txt")]
        text = zf.read(name).decode()
    assert "crowdnav-mesrnn = crowdnav_mesrnn.cli:main" in text
    assert "[crowdnav_mesrnn.predictors]" in text and "mesrnn = crowdnav_mesrnn.predictors:mesrnn" in text
