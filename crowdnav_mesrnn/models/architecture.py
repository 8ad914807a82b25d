"""The architecture of a structural RNN: :class:`ModelConfig` and the meta-path types of each model.

A config fixes everything a network's weights depend on; :class:`~crowdnav_mesrnn.models.structural_rnn.StructuralRNN`
is built from one, checkpoints store :meth:`ModelConfig.to_dict`, and its ``repr`` is part of the forecast cache's
keys (``envs.forecast_cache.predictor_fingerprint``), so both are stable: the distribution head's fields appear only
when they differ from a point model's.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

from crowdnav_mesrnn.config import ConfigError, replace_checked

#: Values of :attr:`ModelConfig.head`.
HEADS: tuple[str, ...] = ("point", "gaussian")
#: Fields of the distribution head with their point-model values: left out of a config's repr and saved dict when
#: they hold these, so a point config's repr and saved dict do not depend on the head's fields.
_POINT_DEFAULTS: dict[str, Any] = {"head": "point", "scale_detach": False}

MODEL_TYPES: dict[str, tuple[str, ...]] = {
    "mesrnn": ("S", "T", "SS", "ST", "TS", "TT"),
    "srnn": ("S", "T"),
    "vlstm": (),
}


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of a structural RNN (paper sizes by default)."""

    model: str = "mesrnn"
    """Which model: ``mesrnn``, ``srnn`` or ``vlstm``; fixes the meta-path types."""
    node_embed: int = 128
    """Node embedding size (paper: 128)."""
    node_hidden: int = 256
    """NodeRNN LSTM hidden size (paper: 256)."""
    edge_embed: int = 64
    """EdgeRNN embedding size (paper: 64)."""
    edge_hidden: int = 128
    """EdgeRNN LSTM hidden size (paper: 128)."""
    dropout: float = 0.0
    """Dropout after the embeddings (training only)."""
    aggregate: str = "sum"
    """How meta-paths are pooled over neighbours: ``sum`` (paper) or ``mean``."""
    feature_scale: float = 1.0
    """Multiplier on edge features before the embedding (1 = paper)."""
    node_input: str = "position"
    """What the node embedding reads: ``position`` (paper) or ``velocity`` (last displacement; scene-independent)."""
    offset: str = "absolute"
    """What the decoder's offset is added to: ``absolute`` (paper: current position) or ``cv_residual``
    (current position plus the last displacement, so the network learns a correction to constant velocity;
    the decoder starts at zero, i.e. the untrained model is exactly constant velocity)."""
    standardise: bool = False
    """Scale every edge feature type and the node input by the inverse of its RMS on the training data
    (fitted once before training, stored with the weights). Off in the paper."""
    head: str = "point"
    """What the decoder predicts: ``point`` (paper: the offset of the next position) or ``gaussian`` (a bivariate
    Gaussian over the next position: the same offset as its mean, plus two scales and a correlation from a
    second linear layer on the node state, :mod:`crowdnav_mesrnn.models.gaussian`; trained by negative
    log-likelihood). The point path is the same arithmetic with either head."""
    scale_detach: bool = False
    """With the gaussian head: the scales and correlation are read from the node state with the gradient stopped,
    so learning them never changes the features the mean (the point forecast) is decoded from."""
    types: tuple[str, ...] = field(default=())
    """Meta-path types; filled from ``model`` (not set by hand)."""

    def __repr__(self) -> str:
        # the head's fields appear only when they are not the point defaults, so a point config's repr (hashed into
        # the forecast cache's keys, envs.forecast_cache.predictor_fingerprint) does not depend on them.
        names = [
            f.name
            for f in fields(self)
            if f.name not in _POINT_DEFAULTS or getattr(self, f.name) != _POINT_DEFAULTS[f.name]
        ]
        return f"ModelConfig({', '.join(f'{n}={getattr(self, n)!r}' for n in names)})"

    def __post_init__(self) -> None:
        if self.model not in MODEL_TYPES:
            raise ConfigError(f"unknown model {self.model!r}; valid models: {', '.join(MODEL_TYPES)}")
        if self.aggregate not in ("sum", "mean"):
            raise ConfigError(f"aggregate must be 'sum' or 'mean', got {self.aggregate!r}")
        if self.node_input not in ("position", "velocity"):
            raise ConfigError(f"node_input must be 'position' or 'velocity', got {self.node_input!r}")
        if self.offset not in ("absolute", "cv_residual"):
            raise ConfigError(f"offset must be 'absolute' or 'cv_residual', got {self.offset!r}")
        if self.head not in HEADS:
            raise ConfigError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")
        if self.scale_detach and self.head != "gaussian":
            raise ConfigError("scale_detach needs head: gaussian")
        if self.types != MODEL_TYPES[self.model]:
            if self.types:
                raise ConfigError(f"types {self.types} do not match model {self.model!r} ({MODEL_TYPES[self.model]})")
            object.__setattr__(self, "types", MODEL_TYPES[self.model])
        for name in ("node_embed", "node_hidden", "edge_embed", "edge_hidden"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        d = dict(d)
        if "types" in d:
            d["types"] = tuple(d["types"])
        return replace_checked(cls(model=d.get("model", "mesrnn")), d, "model config")

    def to_dict(self) -> dict:
        """The config as saved in checkpoints (the head's fields only when not the point defaults, so a point
        config saved without them resumes and compares equal)."""
        out = asdict(self)
        out["types"] = list(self.types)
        for key, default in _POINT_DEFAULTS.items():
            if out[key] == default:
                del out[key]
        return out
