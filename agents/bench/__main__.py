"""``python -m agents.bench ...``: the same as ``crowdnav-mesrnn bench ...``."""

import sys

from agents.bench.cli import main

if __name__ == "__main__":
    sys.exit(main())
