"""Bivariate Gaussians over 2-D positions: the distribution head's parameters, likelihood, regions and samples.

A forecast step's distribution is ``N(mean, Σ)`` with ``Σ = [[σx², ρσxσy], [ρσxσy, σy²]]``. The structural
RNN's distribution head emits three raw numbers per pedestrian and step; :func:`params_from_raw` maps them
to ``σ = softplus(raw) + SIGMA_MIN`` (per axis) and ``ρ = RHO_MAX · tanh(raw)``. Everything here works on
torch tensors and on numpy arrays of any leading shape (``(..., 2)`` means/scales, ``(...)`` correlations).

A ``c`` region is the ellipse ``{y : d²(y) ≤ χ²₂(c)}`` with ``d²`` the squared Mahalanobis distance; for two
dimensions ``χ²₂(c) = −2 ln(1 − c)``, so the region holds probability ``c`` exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import torch

#: Smallest scale, in the units of the head (min-max normalised; about 1 cm on ETH/UCY scenes).
SIGMA_MIN: Final[float] = 1e-3
#: Largest absolute correlation (keeps ``1 − ρ²`` away from 0).
RHO_MAX: Final[float] = 0.95
#: Initial scale of an untrained head (normalised units; ~0.1-0.2 m), set through the head's bias.
SIGMA_INIT: Final[float] = 0.02
LOG_2PI: Final[float] = math.log(2.0 * math.pi)


def params_from_raw(raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sigma (..., 2), rho (...))`` from the head's raw output ``(..., 3)``."""
    sigma = torch.nn.functional.softplus(raw[..., :2]) + SIGMA_MIN
    rho = torch.tanh(raw[..., 2]) * RHO_MAX
    return sigma, rho


def raw_sigma_init() -> float:
    """The raw value whose scale is :data:`SIGMA_INIT` (the inverse of the softplus)."""
    return math.log(math.expm1(SIGMA_INIT - SIGMA_MIN))


def _lib(x: Any) -> Any:
    return torch if isinstance(x, torch.Tensor) else np


def squared_mahalanobis(err: Any, sigma: Any, rho: Any) -> Any:
    """``(...)`` squared Mahalanobis distance of errors ``err = y − mean (..., 2)`` under ``(sigma, rho)``."""
    zx = err[..., 0] / sigma[..., 0]
    zy = err[..., 1] / sigma[..., 1]
    return (zx * zx + zy * zy - 2.0 * rho * zx * zy) / (1.0 - rho * rho)


def nll(err: Any, sigma: Any, rho: Any) -> Any:
    """``(...)`` negative log-density (nats) of errors ``err (..., 2)`` under ``N(0, Σ(sigma, rho))``, in the
    units of ``err`` and ``sigma`` (a density per unit², so metres and normalised units differ by a constant)."""
    lib = _lib(err)
    return (
        LOG_2PI
        + lib.log(sigma[..., 0])
        + lib.log(sigma[..., 1])
        + 0.5 * lib.log(1.0 - rho * rho)
        + 0.5 * squared_mahalanobis(err, sigma, rho)
    )


def chi2_radius(level: float) -> float:
    """The Mahalanobis radius of the ``level`` region of a bivariate Gaussian: ``sqrt(−2 ln(1 − level))``."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"coverage level must lie in (0, 1), got {level!r}")
    return math.sqrt(-2.0 * math.log1p(-level))


def major_semi_axis(sigma: Any, rho: Any) -> Any:
    """``(...)`` the standard deviation along the ellipse's major axis (the square root of Σ's larger
    eigenvalue): a circle of radius ``r · major_semi_axis`` contains the Mahalanobis-``r`` ellipse."""
    lib = _lib(sigma)
    vx, vy = sigma[..., 0] ** 2, sigma[..., 1] ** 2
    cov = rho * sigma[..., 0] * sigma[..., 1]
    half_tr = 0.5 * (vx + vy)
    disc = lib.sqrt(0.25 * (vx - vy) ** 2 + cov * cov)
    return lib.sqrt(half_tr + disc)


def equivalent_radius(sigma: Any, rho: Any) -> Any:
    """``(...)`` the radius of the circle with the area of the Mahalanobis-1 ellipse, ``sqrt(σx σy sqrt(1 − ρ²))``."""
    lib = _lib(sigma)
    return lib.sqrt(sigma[..., 0] * sigma[..., 1] * lib.sqrt(1.0 - rho * rho))


def sample(mean: torch.Tensor, sigma: torch.Tensor, rho: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """``mean + L eps`` with ``L`` the Cholesky factor of ``Σ(sigma, rho)``; ``eps (..., 2)`` standard normal."""
    x = sigma[..., 0] * eps[..., 0]
    y = sigma[..., 1] * (rho * eps[..., 0] + torch.sqrt(1.0 - rho * rho) * eps[..., 1])
    return mean + torch.stack([x, y], dim=-1)


@dataclass(frozen=True)
class GaussianForecast:
    """Per-step bivariate Gaussians of a batch of forecasts (torch tensors).

    Attributes:
        mean: ``(B, P, N, 2)`` the point forecast (the mean rollout), metres.
        sigma: ``(B, P, N, 2)`` standard deviations along x and y, metres.
        rho: ``(B, P, N)`` correlations in ``(−1, 1)``.
    """

    mean: torch.Tensor
    sigma: torch.Tensor
    rho: torch.Tensor

    def draw(self, samples: int, generator: torch.Generator | None = None, coherent: bool = False) -> torch.Tensor:
        """``(B, samples, P, N, 2)`` positions, each step drawn from its Gaussian: independently of the other steps,
        or (``coherent``) with one standard normal draw per sample and pedestrian shared by all steps (a trajectory
        that keeps to the same quantile of every step's Gaussian; each step's distribution is the same)."""
        b, p, n, _ = self.mean.shape
        eps = torch.randn((b, samples, 1 if coherent else p, n, 2), generator=generator, dtype=self.mean.dtype)
        return sample(self.mean[:, None], self.sigma[:, None], self.rho[:, None], eps.expand(b, samples, p, n, 2))
