"""Every code block of the documentation is checked: Python blocks run, shell commands parse.

Python blocks of ``docs/**/*.md`` and ``README.md`` run in order in one namespace per page, in a temporary
working directory holding links to the repository's ``configs/`` and ``examples/`` (so repo-relative paths work
and nothing is written into the checkout). A block preceded by ``<!-- docs-test: skip -->`` is not run; one
preceded by ``<!-- docs-test: requires MODULE -->`` runs only where ``MODULE`` is importable (in CI a missing
module fails). In shell blocks, every ``crowdnav-mesrnn`` command is parsed by the command line's own parser.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([*(ROOT / "docs").rglob("*.md"), ROOT / "README.md"])
MARKER = re.compile(r"<!--\s*docs-test:\s*(skip|requires\s+([\w.]+))\s*-->")
FENCE = re.compile(r"^(\s*)```+\s*([\w+-]*)")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int
    lang: str
    code: str
    marker: str | None
    requires: str | None


def blocks(page: Path) -> list[Block]:
    """The fenced code blocks of a page with the docs-test marker on the line before each."""
    out: list[Block] = []
    lines = page.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, lang = m.group(1), m.group(2).lower()
        fence = lines[i].strip().split(lang)[0] if lang else lines[i].strip()
        start = i
        body: list[str] = []
        i += 1
        while i < len(lines) and not (lines[i].strip().startswith(fence) and lines[i].strip().strip("`") == ""):
            body.append(lines[i][len(indent) :] if lines[i].startswith(indent) else lines[i])
            i += 1
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        mark = MARKER.search(prev)
        out.append(
            Block(
                page,
                start + 1,
                lang,
                "\n".join(body),
                mark.group(1).split()[0] if mark else None,
                mark.group(2) if mark else None,
            )
        )
        i += 1
    return out


def _id(page: Path) -> str:
    return str(page.relative_to(ROOT))


PY_PAGES = [p for p in PAGES if any(b.lang == "python" for b in blocks(p))]


def test_the_scan_sees_the_pages() -> None:
    names = {_id(p) for p in PY_PAGES}
    assert {"README.md", "docs/first-hour.md", "docs/plugins.md", "docs/predictors.md", "docs/env.md"} <= names


@pytest.fixture
def sandbox(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    for name in ("configs", "examples"):
        (tmp_path / name).symlink_to(ROOT / name, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    return tmp_path


#: pages whose blocks take long (first-hour trains a policy and evaluates it): run in CI (``-m "slow or not slow"``)
SLOW_PAGES = {"docs/first-hour.md"}


def _page_param(page: Path) -> object:
    return pytest.param(page, marks=pytest.mark.slow) if _id(page) in SLOW_PAGES else page


@pytest.mark.parametrize("page", [_page_param(p) for p in PY_PAGES], ids=[_id(p) for p in PY_PAGES])
def test_python_blocks_run(page: Path, sandbox: Path, data_dir: Path) -> None:
    namespace: dict[str, object] = {"__name__": "__docs__"}
    ran = 0
    for block in blocks(page):
        if block.lang != "python" or block.marker == "skip":
            continue
        if block.requires and importlib.util.find_spec(block.requires) is None:
            if os.environ.get("CI"):
                pytest.fail(f"{_id(page)}:{block.line}: needs {block.requires}, which CI installs")
            continue
        code = compile(block.code, f"{_id(page)}:{block.line}", "exec")
        with contextlib.redirect_stdout(io.StringIO()):
            try:
                exec(code, namespace)
            except Exception as exc:
                raise AssertionError(
                    f"{_id(page)}:{block.line}: the block failed: {type(exc).__name__}: {exc}"
                ) from exc
        ran += 1
    assert ran or all(b.marker for b in blocks(page) if b.lang == "python")


def _commands(code: str) -> list[list[str]]:
    """``crowdnav-mesrnn`` invocations of a shell block (continuations joined, comments and ``&&`` chains split)."""
    out = []
    for line in code.replace("\\\n", " ").splitlines():
        try:
            words = shlex.split(line, comments=True)
        except ValueError:
            continue
        part: list[str] = []
        for w in [*words, "&&"]:
            if w in ("&&", "||", ";", "|", "&"):
                if part and part[0] == "crowdnav-mesrnn":
                    out.append(part[1:])
                part = []
            else:
                part.append(w)
    return out


SHELL = [(p, b) for p in PAGES for b in blocks(p) if b.lang in ("bash", "sh", "shell") and _commands(b.code)]


@pytest.mark.parametrize(("page", "block"), SHELL, ids=[f"{_id(p)}:{b.line}" for p, b in SHELL])
def test_shell_commands_parse(page: Path, block: Block) -> None:
    from crowdnav_mesrnn.cli import COMMANDS, build_parser

    for argv in _commands(block.code):
        assert argv and argv[0] in COMMANDS, f"{_id(page)}:{block.line}: unknown command crowdnav-mesrnn {argv}"
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                build_parser(argv[0]).parse_args(argv)
            except SystemExit as exc:
                if exc.code:
                    pytest.fail(f"{_id(page)}:{block.line}: `crowdnav-mesrnn {shlex.join(argv)}`: {err.getvalue()}")


#: Widest line of a code block on the pages readers follow, characters: what Material for MkDocs shows without
#: scrolling when both sidebars are visible. Its content column is 61 - 2 x 12.1 (sidebars) - 2 x 1.2 (margins) =
#: 34.4 rem; a code block pads it by 2 x 0.8 rem and sets 0.68 rem monospace characters 0.6 em wide: 80 characters.
CODE_WIDTH = 80
#: The pages held to :data:`CODE_WIDTH`: README.md and the guides in docs/. The pages under docs/results/ are
#: generated reports and recorded outputs, whose printed tables keep their columns (a reader scrolls them).
NARROW_PAGES = [p for p in PAGES if "results" not in p.relative_to(ROOT).parts]


@pytest.mark.parametrize("page", NARROW_PAGES, ids=_id)
def test_code_blocks_fit_the_content_width(page: Path) -> None:
    """No line of a fenced block is cut on the right: long trailing comments go on a line of their own, long
    commands are continued with a backslash."""
    wide = [
        f"{_id(page)}:{block.line + 1 + k}: {len(line)} characters"
        for block in blocks(page)
        for k, line in enumerate(block.code.splitlines())
        if len(line) > CODE_WIDTH
    ]
    assert not wide, f"code lines over {CODE_WIDTH} characters (the docs' content width):\n" + "\n".join(wide)


def test_markers_are_recognised() -> None:
    page = ROOT / "docs" / "plugins.md"
    assert any(b.requires == "kalman_predictor" for b in blocks(page))
