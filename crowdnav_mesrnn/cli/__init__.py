"""The ``crowdnav-mesrnn`` command line: a thin dispatcher over the subcommands each package contributes.

:data:`COMMANDS` names, per subcommand, the ``"module:function"`` that adds its parser; only the module of the
subcommand being run is imported, so ``--help`` stays fast and no lower package imports a higher one. The
predictor side's own subcommands are :mod:`crowdnav_mesrnn.cli.data` and :mod:`crowdnav_mesrnn.cli.predictor`.
:func:`main` is the console script; errors of bad input (missing data, bad config, bad value) exit with 2 and a
one-line message, Ctrl-C with 130.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence
from typing import Any

from crowdnav_mesrnn._deprecated import moved_attributes

#: subcommand -> ("module:function" adding its parser to argparse sub-parsers, one-line help). The module is
#: imported only when its subcommand runs, so no lower package imports a higher one and ``--help`` stays fast.
COMMANDS: dict[str, tuple[str, str]] = {
    "data": ("crowdnav_mesrnn.cli.data:add_parser", "download, inspect and verify the ETH/UCY data"),
    "predictor": ("crowdnav_mesrnn.cli.predictor:add_parser", "train, evaluate, export and plot trajectory predictors"),
    "forecasts": ("envs.cli:add_forecasts", "build and inspect the shared on-disk forecast cache"),
    "demo": ("agents.cli:add_demo", "a policy crosses a held-out ETH/UCY scene with forecasts; metrics and a GIF"),
    "agent": ("agents.cli:add_agent", "train and evaluate navigation policies (PPO, SAC, planners)"),
    "ablation": ("agents.cli:add_ablation", "run the planning-aid ablation grid and summarise it"),
    "bench": ("agents.bench:add_parser", "benchmark any predictor: ADE/FDE vs CV and the planner cells, one page"),
    "bench-policy": (
        "agents.policy_bench:add_parser",
        "benchmark your own policy against the shipped planners and the privileged ceiling, one page",
    ),
}


def _resolve(target: str) -> Callable[[Any], None]:
    module, _, func = target.partition(":")
    return getattr(importlib.import_module(module), func)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (every other subcommand is a stub that lists its help)."""
    from crowdnav_mesrnn._version import __version__

    parser = argparse.ArgumentParser(
        prog="crowdnav-mesrnn", description="MESRNN trajectory prediction and robot crowd navigation on ETH/UCY."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (target, help_text) in COMMANDS.items():
        if name == command:
            _resolve(target)(sub)
        else:
            sub.add_parser(name, help=help_text)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from crowdnav_mesrnn.config import ConfigError
    from crowdnav_mesrnn.data.paths import DataNotFoundError
    from crowdnav_mesrnn.data.recordings import DataFormatError

    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    try:
        if getattr(args, "data_dir_env", None):  # commands whose workers find the data through the variable
            from crowdnav_mesrnn.data.paths import use_data_dir

            use_data_dir(args.data_dir_env)
        return int(args.func(args) or 0)
    except (DataNotFoundError, DataFormatError, ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"crowdnav-mesrnn: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crowdnav-mesrnn: interrupted", file=sys.stderr)
        return 130


__getattr__ = moved_attributes(__name__, {"add_data": "crowdnav_mesrnn.cli.data:add_parser"})
