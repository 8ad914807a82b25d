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
    unknown = set(types) - set(METAPATH_TYPES)
    if unknown:
        raise ValueError(f"unknown meta-path types {sorted(unknown)}; valid: {', '.join(METAPATH_TYPES)}")
    dt = p_t.dtype
    mt, mt1, mt2 = m_t.to(dt).unsqueeze(-1), m_tm1.to(dt).unsqueeze(-1), m_tm2.to(dt).unsqueeze(-1)
    # Zero absent positions so that masked products never see stale or padding values.
    p_t, p_tm1, p_tm2 = p_t * mt, p_tm1 * mt1, p_tm2 * mt2
    out: dict[str, torch.Tensor] = {}
    need_t = {"T", "ST", "TS", "TT"} & set(types)
    need_s_now = {"S", "SS", "ST"} & set(types)
    vel = (p_t - p_tm1) * mt * mt1 if need_t else None
    if need_s_now:
        d, w = _pairwise(p_t, m_t)  # d: (..., N, N, 2), w: (..., N, N)
        wd = d * w.unsqueeze(-1)  # j-present differences p_i − p_j
        if "S" in types or "SS" in types:
            s_raw = wd.sum(-2)  # (..., N, 2): Σ_j (p_i − p_j) over present j (i's own presence ignored)
        if "S" in types:
            out["S"] = s_raw * mt
        if "SS" in types:
            # Σ_{k≠i,j present} (p_j − p_k) = S'_j − (p_j − p_i) = S'_j + D_ij, for present i.
            inner = s_raw.unsqueeze(-3) + d  # (..., i, j, 2): S'_j + D_ij
            out["SS"] = (wd * inner).sum(-2) * mt
        if "ST" in types:
            assert vel is not None
            out["ST"] = (wd * vel.unsqueeze(-3)).sum(-2) * mt
    if "T" in types:
        assert vel is not None
        out["T"] = vel
    if "TS" in types:
        assert vel is not None
        d1, w1 = _pairwise(p_tm1, m_tm1)
        s_prev = (d1 * w1.unsqueeze(-1)).sum(-2)
        out["TS"] = vel * s_prev
    if "TT" in types:
        assert vel is not None
        vel_prev = (p_tm1 - p_tm2) * mt1 * mt2
        out["TT"] = vel * vel_prev
    return {k: out[k] for k in types}


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
