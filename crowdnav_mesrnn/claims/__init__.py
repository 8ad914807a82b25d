"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.claims`."""

from crowdnav_mesrnn._deprecated import warn_moved

warn_moved(__name__, "crowdnav_mesrnn.studies.claims")
