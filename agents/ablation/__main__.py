"""``python -m agents.ablation ...``: see :func:`agents.ablation.cli.main`."""

import sys

from agents.ablation.cli import main

if __name__ == "__main__":
    sys.exit(main())
