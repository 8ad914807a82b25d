"""Trajectory predictors: the structural RNN family (MESRNN, SRNN, VLSTM) and constant velocity."""

from crowdnav_mesrnn.models.base import LEARNED_MODELS, MODELS, ConstantVelocity, Predictor

__all__ = ["LEARNED_MODELS", "MODELS", "ConstantVelocity", "Predictor", "get_predictor"]


def get_predictor(name: str, split: str | None = None) -> Predictor:
    """A ready predictor by name: ``"cv"``, a pretrained ``"mesrnn"``/``"srnn"``/``"vlstm"`` for ``split``, an
    installed plug-in's name or an import path ``package.module:Factory`` (:mod:`crowdnav_mesrnn.predictors`)."""
    if name == "cv":
        return ConstantVelocity()
    if name in LEARNED_MODELS:
        if split is None:
            raise ValueError(f"predictor {name!r} needs the split whose held-out scene it will forecast")
        from crowdnav_mesrnn.models.pretrained import load_pretrained

        return load_pretrained(name, split)
    from crowdnav_mesrnn.predictors import load

    return load(name, split)  # PluginError (a ValueError) names the registered predictors
