"""The command line as a user meets it: help on every option, one verb per action, --data-dir wherever data is read."""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from crowdnav_mesrnn.cli import COMMANDS, build_parser, main
from crowdnav_mesrnn.data.paths import ENV_VAR

#: Commands that read ETH/UCY data, each of which must take --data-dir.
READS_DATA = [
    "data summary",
    "data check",
    "predictor train",
    "predictor evaluate",
    "predictor report",
    "predictor plan",
    "predictor plot",
    "forecasts build",
    "demo",
    "agent train",
    "agent evaluate",
    "ablation",
    "bench",
]


def _leaves(parser: argparse.ArgumentParser, path: list[str]) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path), parser
    for action in subs:
        seen: set[int] = set()
        for name, child in action.choices.items():
            if id(child) not in seen:  # aliases share a parser
                seen.add(id(child))
                yield from _leaves(child, [*path, name])


def all_commands() -> dict[str, argparse.ArgumentParser]:
    out: dict[str, argparse.ArgumentParser] = {}
    for command in COMMANDS:
        for name, parser in _leaves(build_parser(command), []):
            if name.split()[0] == command:
                out[name] = parser
    return out


def test_every_option_has_help() -> None:
    missing = [
        f"{name} {'/'.join(a.option_strings) or a.dest}"
        for name, parser in all_commands().items()
        for a in parser._actions
        if not isinstance(a, argparse._HelpAction) and not a.help
    ]
    assert not missing, f"options without help: {missing}"


@pytest.mark.parametrize("command", READS_DATA)
def test_commands_that_read_data_take_data_dir(command: str) -> None:
    parser = all_commands()[command]
    assert any("--data-dir" in a.option_strings for a in parser._actions), command


def test_one_verb_per_action_across_layers() -> None:
    names = set(all_commands())
    assert {"predictor evaluate", "agent evaluate"} <= names
    assert build_parser("predictor").parse_args(["predictor", "eval", "--model", "cv"]).model == "cv"  # old alias


def test_data_dir_reaches_the_workers_through_the_variable(
    data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "elsewhere"))
    out = tmp_path / "b"
    argv = ["bench", "cv", "--splits", "eth", "--no-planner", "--resamples", "100", "--out", str(out)]
    assert main([*argv, "--data-dir", str(data_dir)]) == 0
    assert os.environ[ENV_VAR] == str(data_dir.resolve())
    assert main(["ablation", "configs/ablation/planning_aid.yaml", "--dry-run", "--data-dir", str(tmp_path)]) == 2
    assert "no ETH/UCY data found" in capsys.readouterr().err


def test_data_check_defaults_to_the_folder_the_project_uses(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "check"]) == 0
    assert str(data_dir) in capsys.readouterr().out
