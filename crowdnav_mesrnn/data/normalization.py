"""Min-max normalisation of positions to [-1, 1], as in the MESRNN paper."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from crowdnav_mesrnn.data.recordings import Recording


@dataclass(frozen=True)
class MinMax:
    """Per-axis min-max map of metres to [-1, 1]; fitted on training data only.

    ``normalise(p) = 2 (p - lo) / (hi - lo) - 1``; differences scale by ``2 / (hi - lo)``.
    """

    lo: tuple[float, float]
    hi: tuple[float, float]

    @classmethod
    def fit(cls, positions: np.ndarray) -> MinMax:
        """Fit on ``(..., 2)`` positions in metres."""
        pts = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            raise ValueError("cannot fit normalisation on zero positions")
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        if np.any(hi - lo <= 0):
            raise ValueError(f"degenerate range for normalisation: min {lo}, max {hi}")
        return cls((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))

    @classmethod
    def fit_recordings(cls, recordings: list[Recording]) -> MinMax:
        return cls.fit(np.concatenate([r.positions[r.present] for r in recordings], axis=0))

    @property
    def scale(self) -> np.ndarray:
        """``(2,)`` normalised units per metre."""
        return 2.0 / (np.asarray(self.hi) - np.asarray(self.lo))

    def normalise(self, p: Any) -> Any:
        """Metres -> [-1, 1]; works on numpy arrays and torch tensors of shape ``(..., 2)``."""
        lo, sc = self._as(p, self.lo), self._as(p, self.scale)
        return (p - lo) * sc - 1.0

    def denormalise(self, q: Any) -> Any:
        """Inverse of :meth:`normalise`."""
        lo, sc = self._as(q, self.lo), self._as(q, self.scale)
        return (q + 1.0) / sc + lo

    @staticmethod
    def _as(like: Any, values: Any) -> Any:
        arr = np.asarray(values, dtype=np.float64)
        if hasattr(like, "new_tensor"):
            return like.new_tensor(arr)
        return arr.astype(np.asarray(like).dtype if np.asarray(like).dtype.kind == "f" else np.float64)

    def to_dict(self) -> dict[str, list[float]]:
        return {"lo": list(self.lo), "hi": list(self.hi)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MinMax:
        try:
            return cls(tuple(map(float, d["lo"])), tuple(map(float, d["hi"])))  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"bad normalisation statistics {d!r}: need 'lo' and 'hi' pairs") from exc
