"""``python -m crowdnav_mesrnn.cli``: the ``crowdnav-mesrnn`` command."""

import sys

from crowdnav_mesrnn.cli import main

sys.exit(main())
