"""The command line imports the layers, never the reverse: no module of ``agents`` but ``agents/cli.py`` imports it."""

from __future__ import annotations

import ast
from pathlib import Path

import agents

AGENTS = Path(agents.__file__).resolve().parent


def _imports_agents_cli(path: Path) -> list[int]:
    """Lines of ``path`` importing ``agents.cli`` (``import agents.cli``, ``from agents.cli import ...``,
    ``from agents import cli``), at module level or inside a function."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import) and any(a.name == "agents.cli" for a in node.names):
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and (
            node.module == "agents.cli" or (node.module == "agents" and any(a.name == "cli" for a in node.names))
        ):
            lines.append(node.lineno)
    return lines


def test_no_layer_module_imports_the_agents_command_line() -> None:
    modules = sorted(AGENTS.rglob("*.py"))
    assert (
        AGENTS / "training" / "run.py" in modules and AGENTS / "ablation" / "backends.py" in modules
    )  # the scan sees them
    offenders = {
        f"{path.relative_to(AGENTS.parent)}:{line}"
        for path in modules
        if path != AGENTS / "cli.py"
        for line in _imports_agents_cli(path)
    }
    assert not offenders, f"layer modules import agents.cli: {sorted(offenders)}"
