"""The environment's subcommands of ``crowdnav-mesrnn``: ``forecasts``.

:func:`add_forecasts` is named in :data:`crowdnav_mesrnn.cli.COMMANDS` and imported only when the
subcommand runs.
"""

from __future__ import annotations

import sys
from typing import Any


def add_forecasts(sub: Any) -> None:
    p = sub.add_parser("forecasts", help="build and inspect the shared on-disk forecast cache")
    p.set_defaults(func=lambda args: _not_yet())


def _not_yet() -> int:
    print("crowdnav-mesrnn forecasts: not implemented yet", file=sys.stderr)
    return 2
