"""The RL side of crowdnav-mesrnn: SB3 feature extractors, training, evaluation, ablation."""
