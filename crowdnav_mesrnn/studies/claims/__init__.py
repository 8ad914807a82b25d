"""Tests of the MESRNN paper's further claims (density, motion type, social compliance, scene
difficulty) on the leave-one-out test sets; the declaration is :mod:`crowdnav_mesrnn.studies.claims.declared`."""
