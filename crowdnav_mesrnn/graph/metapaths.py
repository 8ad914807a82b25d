"""Spatio-temporal graph features: spatial/temporal edges and their length-2 meta-paths.

Notation (paper, eqs. 1-4): ``p_i(t)`` position of pedestrian ``i`` at step ``t``;
``d`` is the difference of positions and the composition ``⊙`` of two edges is the element-wise
product of their 2-D vectors. For pedestrian ``i`` present at ``t`` (all features are 0 otherwise):

- ``S_i(t)  = Σ_j (p_i(t) − p_j(t))``
- ``T_i(t)  = p_i(t) − p_i(t−1)``                                  (needs ``i`` at ``t−1``)
- ``SS_i(t) = Σ_j Σ_{k≠i,j} (p_i(t) − p_j(t)) ⊙ (p_j(t) − p_k(t))``
- ``ST_i(t) = Σ_j (p_i(t) − p_j(t)) ⊙ T_j(t)``                     (``j`` at ``t`` and ``t−1``)
- ``TS_i(t) = Σ_j T_i(t) ⊙ (p_i(t−1) − p_j(t−1))``                (``j`` at ``t−1``)
- ``TT_i(t) = T_i(t) ⊙ T_i(t−1)``                                  (``i`` at ``t``, ``t−1``, ``t−2``)

Sums run over neighbours ``j ≠ i`` (and ``k``) present at the times involved. Everything is
computed with pairwise differences, ``O(N²)`` per step, with no Python loop over pedestrians;
``SS`` factors its double sum as ``Σ_j D_ij ⊙ (S'_j + D_ij)`` where ``D_ij = p_i − p_j`` and
``S'_j = Σ_k (p_j − p_k)`` over present ``k``.
"""

from __future__ import annotations

from typing import Final

import torch

METAPATH_TYPES: Final[tuple[str, ...]] = ("S", "T", "SS", "ST", "TS", "TT")


def _pairwise(p: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``D[..., i, j, :] = p_i − p_j`` and the neighbour weight ``W[..., i, j] = m_j`` (0 on the diagonal)."""
    d = p.unsqueeze(-2) - p.unsqueeze(-3)
    w = m.unsqueeze(-2).to(p.dtype).expand(*m.shape, m.shape[-1])
    return d, w


def metapath_features_step(
    p_t: torch.Tensor,
    p_tm1: torch.Tensor,
    p_tm2: torch.Tensor,
    m_t: torch.Tensor,
    m_tm1: torch.Tensor,
    m_tm2: torch.Tensor,
    types: tuple[str, ...] = METAPATH_TYPES,
) -> dict[str, torch.Tensor]:
    """Meta-path features at one step from positions at ``t``, ``t−1`` and ``t−2``.

    Args:
        p_t, p_tm1, p_tm2: ``(..., N, 2)`` positions (any consistent unit); values where the
            mask is False are ignored.
        m_t, m_tm1, m_tm2: ``(..., N)`` bool presence masks (pass all-False for steps before
            the start of a sequence).
        types: which features to compute (subset of :data:`METAPATH_TYPES`).

    Returns:
        ``{type: (..., N, 2)}`` summed features; zero for absent pedestrians.
    """
    dt = p_t.dtype
    w = tuple(m.to(dt).unsqueeze(-1) for m in (m_t, m_tm1, m_tm2))
    feats, _ = stacked_features_step(p_t, p_tm1, p_tm2, w[0], w[1], w[2], types)
    return dict(zip(types, feats.unbind(0), strict=True))


def stacked_features_step(
    p_t: torch.Tensor,
    p_tm1: torch.Tensor,
    p_tm2: torch.Tensor,
    w_t: torch.Tensor | None,
    w_tm1: torch.Tensor | None,
    w_tm2: torch.Tensor | None,
    types: tuple[str, ...] = METAPATH_TYPES,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`metapath_features_step` with presence as float ``(..., N, 1)`` weights (0 or 1), stacked.

    All three weights ``None`` means every pedestrian is present at all three steps: the products by the
    weights (all exactly 1) are skipped, which gives the same values to the bit with fewer operations.

    Returns:
        ``(len(types), ..., N, 2)`` features in the order of ``types`` and the velocity
        ``T = (p_t − p_{t−1})`` of pedestrians present at both steps, ``(..., N, 2)`` (0 otherwise).
    """
    unknown = set(types) - set(METAPATH_TYPES)
    if unknown:
        raise ValueError(f"unknown meta-path types {sorted(unknown)}; valid: {', '.join(METAPATH_TYPES)}")
    dense = w_t is None
    if dense != (w_tm1 is None) or dense != (w_tm2 is None):
        raise ValueError("give all three presence weights, or none (everyone present)")

    def times(x: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
        return x if w is None else x * w

    # Zero absent positions so that masked products never see stale or padding values (0/1 products are exact).
    p_t, p_tm1 = times(p_t, w_t), times(p_tm1, w_tm1)
    vel = p_t - p_tm1 if dense else (p_t - p_tm1) * (w_t * w_tm1)  # type: ignore[operator]
    out: dict[str, torch.Tensor] = {"T": vel}
    if {"S", "SS", "ST"} & set(types):
        d = p_t.unsqueeze(-2) - p_t.unsqueeze(-3)  # (..., i, j, 2): p_i − p_j
        wd = d if w_t is None else d * w_t.unsqueeze(-3)  # j-present differences (i's own presence is applied last)
        if "S" in types or "SS" in types:
            s_raw = wd.sum(-2)  # (..., N, 2): Σ_j (p_i − p_j) over present j
            out["S"] = times(s_raw, w_t)
            if "SS" in types:
                # Σ_{k≠i,j present} (p_j − p_k) = S'_j − (p_j − p_i) = S'_j + D_ij, for present i.
                out["SS"] = times((wd * (s_raw.unsqueeze(-3) + d)).sum(-2), w_t)
        if "ST" in types:
            out["ST"] = times((wd * vel.unsqueeze(-3)).sum(-2), w_t)
    if "TS" in types:
        d_prev = p_tm1.unsqueeze(-2) - p_tm1.unsqueeze(-3)
        s_prev = (d_prev if w_tm1 is None else d_prev * w_tm1.unsqueeze(-3)).sum(-2)
        out["TS"] = vel * s_prev
    if "TT" in types:
        if dense:
            out["TT"] = vel * (p_tm1 - p_tm2)
        else:
            out["TT"] = vel * ((p_tm1 - p_tm2 * w_tm2) * (w_tm1 * w_tm2))  # type: ignore[operator]
    if not types:
        return vel.new_zeros(0, *vel.shape), vel
    return torch.stack([out[k] for k in types]), vel


def dense_features_linear(
    p_t: torch.Tensor, p_tm1: torch.Tensor, p_tm2: torch.Tensor, types: tuple[str, ...] = METAPATH_TYPES
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`stacked_features_step` for ``(N, 2)`` positions with everyone present at all three steps, in ``O(N)``:
    the sums over neighbours are expanded (``S_i = N p_i − Σ_j p_j``; ``ST_i = p_i ⊙ Σ_j T_j − Σ_j p_j ⊙ T_j``;
    ``SS_i = p_i ⊙ Σ_j S_j − Σ_j p_j ⊙ S_j + N p_i² − 2 p_i ⊙ Σ_j p_j + Σ_j p_j²``; ``TS`` like ``S`` at ``t − 1``).
    The same function, rounded differently (sums of positions instead of sums of differences: for the min-max
    normalised positions of the predictors, within float32 rounding of the pairwise form times ``N``); used by
    the online forecast only."""
    n = float(p_t.shape[0])
    vel = p_t - p_tm1
    out: dict[str, torch.Tensor] = {"T": vel}
    if {"S", "SS", "ST"} & set(types):
        total = p_t.sum(0)
        s_raw = p_t * n - total
        out["S"] = s_raw
        if "SS" in types:
            out["SS"] = p_t * (s_raw.sum(0) - 2.0 * total + n * p_t) - (p_t * s_raw).sum(0) + (p_t * p_t).sum(0)
        if "ST" in types:
            out["ST"] = p_t * vel.sum(0) - (p_t * vel).sum(0)
    if "TS" in types:
        out["TS"] = vel * (p_tm1 * n - p_tm1.sum(0))
    if "TT" in types:
        out["TT"] = vel * (p_tm1 - p_tm2)
    if not types:
        return vel.new_zeros(0, *vel.shape), vel
    return torch.stack([out[k] for k in types]), vel


def metapath_features(
    positions: torch.Tensor, mask: torch.Tensor, types: tuple[str, ...] = METAPATH_TYPES
) -> dict[str, torch.Tensor]:
    """Meta-path features at every step of a sequence.

    Args:
        positions: ``(..., T, N, 2)`` positions, any float dtype.
        mask: ``(..., T, N)`` bool presence.
        types: subset of :data:`METAPATH_TYPES` to compute.

    Returns:
        ``{type: (..., T, N, 2)}``; temporal terms are 0 at ``t = 0`` (and ``t <= 1`` for ``TT``).
    """
    if positions.shape[-1] != 2 or positions.shape[:-1] != mask.shape:
        raise ValueError(
            f"positions must be (..., T, N, 2) and mask (..., T, N); got {tuple(positions.shape)} and {tuple(mask.shape)}"
        )
    mask = mask.bool()

    def shift(x: torch.Tensor, k: int, fill: float | bool) -> torch.Tensor:
        t_dim = mask.dim() - 2  # index of T in mask; positions have one extra trailing dim
        if k == 0:
            return x
        pad_shape = list(x.shape)
        pad_shape[t_dim] = min(k, x.shape[t_dim])
        pad = torch.full(pad_shape, fill, dtype=x.dtype, device=x.device)
        body = x.narrow(t_dim, 0, max(x.shape[t_dim] - k, 0))
        return torch.cat([pad, body], dim=t_dim)

    p1, p2 = shift(positions, 1, 0.0), shift(positions, 2, 0.0)
    m1, m2 = shift(mask, 1, False), shift(mask, 2, False)
    return metapath_features_step(positions, p1, p2, mask, m1, m2, types)
