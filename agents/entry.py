"""The ``main()`` of the ``python -m agents.<module>`` commands (``agents.train``, ``agents.evaluate``), and
their ``--set key=value`` options (:func:`parse_set`).

A neutral module: the layers import it, and it imports no layer and no command line (``agents.cli`` imports the
layers, never the reverse).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any

import yaml

from crowdnav_mesrnn.config import ConfigError


def module_main(
    prog: str,
    doc: str | None,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], int],
    argv: Sequence[str] | None = None,
) -> int:
    """``main()`` of a ``python -m agents.<module>`` command: parse, run, and turn configuration and input errors
    into a message and exit status 2 (as ``crowdnav-mesrnn`` does). The description is ``doc``'s first
    paragraph."""
    parser = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0] or None)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        if getattr(args, "data_dir_env", None):
            from crowdnav_mesrnn.data.paths import use_data_dir

            use_data_dir(args.data_dir_env)
        return run(args)
    except (ConfigError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def parse_set(items: Sequence[str] | None) -> dict[str, Any]:
    """``["key=value", ...]`` to a dict, values read as YAML (``1e-4``, ``true``, ``[64, 64]``, ``null``)."""
    out: dict[str, Any] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects key=value, got {item!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out
