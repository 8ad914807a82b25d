"""``python -m agents.policy_bench ...``: the same as ``crowdnav-mesrnn bench-policy ...``."""

import sys

from agents.policy_bench.cli import main

if __name__ == "__main__":
    sys.exit(main())
