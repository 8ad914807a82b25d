"""Spatio-temporal graph features (spatial and temporal edges, length-2 meta-paths)."""

from crowdnav_mesrnn.graph.metapaths import METAPATH_TYPES, metapath_features, metapath_features_step

__all__ = ["METAPATH_TYPES", "metapath_features", "metapath_features_step"]
