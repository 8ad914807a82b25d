"""``cv_gaussian``: constant velocity with an isotropic Gaussian whose scale grows linearly with the horizon.

The trivial distributional baseline every distribution head must beat (issue 30). At horizon step ``h`` (1..12
annotation steps after the last observed one) a pedestrian's position is

    ``N(m_h, σ_h² I)``,   ``σ_h = a + b·h``   (metres; ``a ≥ 0``, ``b ≥ 0``, ``a + b > 0``),

with ``m_h`` exactly the forecast of :class:`~crowdnav_mesrnn.models.base.ConstantVelocity` (the last observed
displacement extrapolated; it is called, not re-implemented). ``a`` and ``b`` are fitted per leave-one-out split by
maximum likelihood on the split's training windows (:mod:`crowdnav_mesrnn.models.cv_gaussian_fit`) and shipped as
``crowdnav_mesrnn/pretrained/cv_gaussian_<split>.json``.

The distribution takes the form of the structural RNN's distribution head: a
:class:`~crowdnav_mesrnn.models.gaussian.GaussianForecast` of means ``(B, P, N, 2)``, per-axis scales
``(B, P, N, 2)`` (here ``σx = σy = σ_h``) and correlations ``(B, P, N)`` (here 0), so the project's NLL
(:func:`crowdnav_mesrnn.models.gaussian.nll`), regions and sampling apply unchanged. Samples are drawn by
:meth:`GaussianForecast.draw`: ``coherent`` (one standard normal draw per sample and pedestrian shared by all 12
steps: a trajectory at one quantile of every step's Gaussian) or marginal (one draw per step). Each step's
distribution is the same either way; only the dependence between steps differs. A step is one annotation of the
recording (0.4 s; 0.667 s on ``biwi_eth``), as for every predictor of the project.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS, check_split
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.base import ConstantVelocity, check_history
from crowdnav_mesrnn.models.gaussian import GaussianForecast

#: The registry name of the predictor.
NAME: Final[str] = "cv_gaussian"
#: Version of the parameter file's layout.
PARAMS_FORMAT: Final[int] = 1
#: The candidate forms of the scale, each a constraint on ``(a, b)``: both free, ``a = 0``, ``b = 0``.
FORMS: Final[tuple[str, ...]] = ("a+b*h", "b*h", "a")
#: Where the shipped parameter files live.
PARAMS_DIR: Final[Path] = Path(__file__).resolve().parent.parent / "pretrained"
#: Keys every parameter file holds (:func:`load_params` rejects a file missing one).
REQUIRED_KEYS: Final[tuple[str, ...]] = (
    "format",
    "model",
    "split",
    "form",
    "a_m",
    "b_m",
    "candidates",
    "selection",
    "data",
    "fit",
    "code_version",
)
#: Keys of each entry of ``candidates`` in a parameter file.
CANDIDATE_KEYS: Final[tuple[str, ...]] = ("a_m", "b_m", "train_nll", "val_nll")


class CvGaussianParamsError(ValueError):
    """A ``cv_gaussian`` parameter file is missing, malformed or out of range; the message names file and key."""


@dataclass(frozen=True)
class CvGaussianParams:
    """The scale ``σ_h = a + b·h`` of the Gaussian at horizon step ``h = 1..pred_len``.

    Raises ``ValueError`` naming the field when a value is not finite, negative, both are 0, or ``form`` is unknown
    or not met (``b*h`` needs ``a_m == 0``, ``a`` needs ``b_m == 0``).
    """

    a_m: float
    """Scale at every step, metres."""
    b_m: float
    """Growth of the scale per annotation step, metres per step."""
    form: str = "a+b*h"
    """Which candidate form (:data:`FORMS`) the values come from."""

    def __post_init__(self) -> None:
        for key in ("a_m", "b_m"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{key} must be a finite number, got {value!r}")
            if value < 0:
                raise ValueError(f"{key} must be >= 0, got {value!r}")
        if not self.a_m + self.b_m > 0:
            raise ValueError(f"a_m + b_m must be > 0 (a scale of 0 has no density), got {self.a_m!r} + {self.b_m!r}")
        if self.form not in FORMS:
            raise ValueError(f"form must be one of {', '.join(FORMS)}, got {self.form!r}")
        if self.form == "b*h" and self.a_m != 0:
            raise ValueError(f"form 'b*h' has a_m == 0, got a_m = {self.a_m!r}")
        if self.form == "a" and self.b_m != 0:
            raise ValueError(f"form 'a' has b_m == 0, got b_m = {self.b_m!r}")

    def sigma_m(self, pred_len: int = PRED_LEN) -> np.ndarray:
        """``(pred_len,)`` float64 scales ``a + b·h`` of steps ``h = 1..pred_len``, metres."""
        return self.a_m + self.b_m * np.arange(1, pred_len + 1, dtype=np.float64)


def isotropic_nll(err: Any, sigma: Any) -> Any:
    """``(...)`` negative log-density (nats, densities per m²) of errors ``err (..., 2)`` metres under ``N(0, σ² I)``
    with ``sigma (...)`` metres: the project's bivariate NLL (:func:`gaussian.nll`) with equal scales and no
    correlation, ``log 2π + 2 log σ + |err|² / (2σ²)``. Works on numpy arrays and torch tensors."""
    lib = torch if isinstance(sigma, torch.Tensor) else np
    return gaussian.nll(err, lib.stack([sigma, sigma], -1), sigma * 0.0)


def cv_mean_batch(
    positions_m: torch.Tensor, mask: torch.Tensor, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN
) -> torch.Tensor:
    """``(B, >=obs_len, N, 2)`` metres (only the first ``obs_len`` steps are read) + ``(B, >=obs_len, N)`` mask ->
    ``(B, pred_len, N, 2)`` float32 metres: :meth:`ConstantVelocity.forecast` applied to every pedestrian of every
    window at once (a batch function for :mod:`crowdnav_mesrnn.evaluation`)."""
    b, _, n, _ = positions_m.shape
    obs = positions_m[:, :obs_len].detach().cpu().float().numpy()
    m = mask[:, :obs_len].detach().cpu().bool().numpy()
    # Constant velocity treats pedestrians independently: the batch is one window of B·N pedestrians.
    flat = ConstantVelocity(obs_len, pred_len).forecast(
        obs.transpose(1, 0, 2, 3).reshape(obs_len, b * n, 2), m.transpose(1, 0, 2).reshape(obs_len, b * n)
    )
    return torch.from_numpy(flat.reshape(b, n, pred_len, 2).transpose(0, 2, 1, 3).copy())


class CvGaussian:
    """Constant velocity with the isotropic Gaussian ``N(m_h, (a + b·h)² I)`` at horizon step ``h``.

    Implements the forecast protocol (:class:`~crowdnav_mesrnn.models.base.Predictor`) and the batched and
    distribution methods of :class:`~crowdnav_mesrnn.models.learned.LearnedPredictor` with a distribution head
    (``predict_batch``, ``predict_distribution_batch``, ``sample_batch``, ``forecast_distribution``), with the same
    shapes and units.

    Args:
        params: the scale's parameters.
        split: the leave-one-out split they were fitted for (None for hand-set parameters).
        info: the parameter file's record (shown in results), if loaded from one.
    """

    name = NAME
    has_distribution = True

    def __init__(
        self,
        params: CvGaussianParams,
        split: str | None = None,
        info: Mapping[str, Any] | None = None,
        obs_len: int = OBS_LEN,
        pred_len: int = PRED_LEN,
    ) -> None:
        self.params = params
        self.split = split
        self.info = dict(info or {})
        self.obs_len = obs_len
        self.pred_len = pred_len
        self._cv = ConstantVelocity(obs_len, pred_len)

    def __repr__(self) -> str:
        p = self.params
        return f"CvGaussian(a_m={p.a_m:.6g}, b_m={p.b_m:.6g}, form={p.form!r}, split={self.split!r})"

    def sigma_m(self, pred_len: int | None = None) -> np.ndarray:
        """``(pred_len,)`` float64 scale of each horizon step ``h = 1..pred_len``, metres (the same in x and y)."""
        return self.params.sigma_m(self.pred_len if pred_len is None else pred_len)

    def cache_fingerprint(self) -> str:
        """A digest of what determines the forecasts (the form and ``a``, ``b`` to the bit, the window lengths)."""
        p = self.params
        key = json.dumps([NAME, p.form, float(p.a_m).hex(), float(p.b_m).hex(), self.obs_len, self.pred_len])
        return hashlib.sha256(key.encode()).hexdigest()

    # ------------------------------------------------------------------ one window (numpy)
    def forecast(self, history: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``(obs_len, N, 2)`` metres + ``(obs_len, N)`` mask -> ``(N, pred_len, 2)`` float32 metres: the
        constant-velocity forecast (:meth:`ConstantVelocity.forecast`), which is the mean of the distribution."""
        return self._cv.forecast(history, mask)

    def forecast_distribution(self, history: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`forecast` with each step's Gaussian, as :meth:`LearnedPredictor.forecast_distribution`.

        Returns:
            ``mean (N, pred_len, 2)`` metres (equal to :meth:`forecast`), ``sigma (N, pred_len, 2)`` metres and
            ``rho (N, pred_len)`` (0), float32; pedestrians absent at the last observed step have scales 0.
        """
        history, mask = check_history(history, mask, self.obs_len)
        mean = self._cv.forecast(history, mask)
        n = mean.shape[0]
        sigma = np.broadcast_to(self.sigma_m().astype(np.float32)[None, :, None], (n, self.pred_len, 2)).copy()
        sigma[~mask[-1]] = 0.0
        return mean, sigma, np.zeros((n, self.pred_len), np.float32)

    # ------------------------------------------------------------------ batches (torch)
    def predict_batch(
        self, positions_m: torch.Tensor, mask: torch.Tensor, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN
    ) -> torch.Tensor:
        """The mean of the distribution for a batch (:func:`cv_mean_batch`)."""
        return cv_mean_batch(positions_m, mask, obs_len, pred_len)

    def predict_distribution_batch(
        self, positions_m: torch.Tensor, mask: torch.Tensor, obs_len: int = OBS_LEN, pred_len: int = PRED_LEN
    ) -> GaussianForecast:
        """The means of :meth:`predict_batch` with scales ``(B, pred_len, N, 2)`` metres (``a + b·h`` for every
        pedestrian and axis) and correlations ``(B, pred_len, N)`` (0)."""
        mean = self.predict_batch(positions_m, mask, obs_len, pred_len)
        b, _, n, _ = mean.shape
        steps = torch.as_tensor(self.sigma_m(pred_len), dtype=mean.dtype)
        sigma = steps.view(1, pred_len, 1, 1).expand(b, pred_len, n, 2).contiguous()
        return GaussianForecast(mean, sigma, torch.zeros((b, pred_len, n), dtype=mean.dtype))

    def sample_batch(
        self,
        positions_m: torch.Tensor,
        mask: torch.Tensor,
        samples: int,
        generator: torch.Generator | None = None,
        feedback: bool = False,
        obs_len: int = OBS_LEN,
        pred_len: int = PRED_LEN,
        coherent: bool = False,
    ) -> torch.Tensor:
        """Sampled futures ``(B, samples, pred_len, N, 2)`` metres, drawn by :meth:`GaussianForecast.draw`.

        Args:
            feedback: must be False: constant velocity has no state for a drawn position to be fed back into.
            coherent: one standard normal draw per sample and pedestrian shared by all steps (each sample keeps to
                one quantile of every step's Gaussian) instead of one draw per step (marginal).
        """
        if feedback:
            raise ValueError(
                "cv_gaussian has no feedback sampling (constant velocity keeps no state to feed a draw back into); "
                "use coherent or marginal sampling"
            )
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        dist = self.predict_distribution_batch(positions_m, mask, obs_len, pred_len)
        return dist.draw(samples, generator, coherent=coherent)


# ---------------------------------------------------------------------------- parameter files


def params_path(split: str, params_dir: str | os.PathLike[str] | None = None) -> Path:
    """``<params_dir>/cv_gaussian_<split>.json`` (default: the shipped folder :data:`PARAMS_DIR`)."""
    check_split(split)
    return Path(params_dir if params_dir is not None else PARAMS_DIR) / f"{NAME}_{split}.json"


def _number(path: Path, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CvGaussianParamsError(f"{path}: key {key!r} must be a finite number, got {value!r}")
    return float(value)


def validate_record(record: Any, path: str | os.PathLike[str], split: str | None = None) -> CvGaussianParams:
    """Check a parameter file's content and return its parameters.

    Checks: every key of :data:`REQUIRED_KEYS`; ``format``, ``model`` and (when given) ``split`` as expected;
    ``a_m``, ``b_m`` finite, ``>= 0``, not both 0, and meeting ``form``; ``candidates`` holding every form of
    :data:`FORMS` with finite, non-negative ``a_m``/``b_m`` and finite NLLs, the selected one equal to the top-level
    ``a_m``/``b_m``.

    Raises:
        CvGaussianParamsError: naming ``path`` and the first bad key (dotted for nested keys).
    """
    path = Path(path)
    if not isinstance(record, dict):
        raise CvGaussianParamsError(f"{path}: expected a JSON object, got {type(record).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in record]
    if missing:
        raise CvGaussianParamsError(f"{path}: missing key {missing[0]!r} (required: {', '.join(REQUIRED_KEYS)})")
    if record["format"] != PARAMS_FORMAT:
        raise CvGaussianParamsError(f"{path}: key 'format' must be {PARAMS_FORMAT}, got {record['format']!r}")
    if record["model"] != NAME:
        raise CvGaussianParamsError(f"{path}: key 'model' must be {NAME!r}, got {record['model']!r}")
    if record["split"] not in SPLITS or (split is not None and record["split"] != split):
        want = repr(split) if split is not None else f"one of {', '.join(SPLITS)}"
        raise CvGaussianParamsError(f"{path}: key 'split' must be {want}, got {record['split']!r}")
    if record["form"] not in FORMS:
        raise CvGaussianParamsError(f"{path}: key 'form' must be one of {', '.join(FORMS)}, got {record['form']!r}")
    a = _number(path, "a_m", record["a_m"])
    b = _number(path, "b_m", record["b_m"])
    for key, value in (("a_m", a), ("b_m", b)):
        if value < 0:
            raise CvGaussianParamsError(f"{path}: key {key!r} must be >= 0, got {value!r}")
    if not a + b > 0:
        raise CvGaussianParamsError(f"{path}: keys 'a_m' and 'b_m' are both 0 (a scale of 0 has no density)")
    fixed = {"b*h": "a_m", "a": "b_m"}.get(record["form"])
    if fixed is not None and record[fixed] != 0:
        raise CvGaussianParamsError(
            f"{path}: key {fixed!r} must be 0 under form {record['form']!r}, got {record[fixed]!r}"
        )
    params = CvGaussianParams(a, b, record["form"])
    cands = record["candidates"]
    if not isinstance(cands, dict):
        raise CvGaussianParamsError(f"{path}: key 'candidates' must be an object, got {type(cands).__name__}")
    for form in FORMS:
        if not isinstance(cands.get(form), dict):
            raise CvGaussianParamsError(
                f"{path}: key 'candidates.{form}' must be an object of {', '.join(CANDIDATE_KEYS)}"
            )
        for key in CANDIDATE_KEYS:
            full = f"candidates.{form}.{key}"
            if key not in cands[form]:
                raise CvGaussianParamsError(f"{path}: missing key {full!r}")
            value = _number(path, full, cands[form][key])
            if key in ("a_m", "b_m") and value < 0:
                raise CvGaussianParamsError(f"{path}: key {full!r} must be >= 0, got {value!r}")
    chosen = cands[params.form]
    if (chosen["a_m"], chosen["b_m"]) != (a, b):
        raise CvGaussianParamsError(
            f"{path}: keys 'a_m', 'b_m' ({a!r}, {b!r}) differ from the selected candidate "
            f"'candidates.{params.form}' ({chosen['a_m']!r}, {chosen['b_m']!r})"
        )
    return params


def load_params(path: str | os.PathLike[str], split: str | None = None) -> tuple[CvGaussianParams, dict[str, Any]]:
    """Read and validate a parameter file (:func:`validate_record`); returns the parameters and the whole record.

    Raises:
        CvGaussianParamsError: the file is missing, is not JSON, or fails validation (naming file and key).
    """
    path = Path(path)
    if not path.is_file():
        raise CvGaussianParamsError(
            f"no cv_gaussian parameters at {path}. Fit them with `python -m crowdnav_mesrnn.models.cv_gaussian_fit "
            f"--split {split or 'all'} --out-dir {path.parent}`"
        )
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CvGaussianParamsError(f"{path}: not valid JSON ({exc})") from None
    return validate_record(record, path, split), record


def load_cv_gaussian(split: str, params_dir: str | os.PathLike[str] | None = None) -> CvGaussian:
    """The ``cv_gaussian`` predictor of ``split`` (its scale fitted on the split's training pieces only), from
    ``cv_gaussian_<split>.json`` in ``params_dir`` (default: the shipped files)."""
    path = params_path(split, params_dir)
    params, record = load_params(path, split)
    return CvGaussian(params, split=split, info=record)
