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


def dense_features_centred(
    p_t: torch.Tensor, p_tm1: torch.Tensor, p_tm2: torch.Tensor, types: tuple[str, ...] = METAPATH_TYPES
) -> tuple[torch.Tensor, torch.Tensor, tuple[float, ...]]:
    """:func:`stacked_features_step` for ``(N, 2)`` positions with everyone present at all three steps, in ``O(N)``
    and few operations, with each type's constant factor left out.

    With ``d_i = p_i − c`` (``c`` the centroid at ``t``) and ``Σ_j d_j = 0`` the sums over neighbours are
    ``S_i = N d_i``, ``SS_i = N d_i² − (N − 1) Σ_j d_j²``, ``ST_i = d_i ⊙ Σ_j T_j − Σ_j d_j ⊙ T_j`` and
    ``TS_i = N T_i ⊙ (p_{t−1,i} − c_{t−1})``. Returned without the factor ``N`` of ``S``, ``SS`` and ``TS``: the
    features times ``factors`` (one per type) equal :func:`stacked_features_step` up to float rounding (the centred
    form rounds like the pairwise sums, not like sums of raw positions). Used by the online forecast, which folds
    ``factors`` into the edge embedding's weights.

    Returns:
        ``(len(types), N, 2)`` features, the ``(N, 2)`` velocity and the per-type factors.
    """
    n = p_t.shape[0]
    vel = p_t - p_tm1
    out: dict[str, torch.Tensor] = {"T": vel}
    factor = {"S": float(n), "SS": float(n), "TS": float(n)}
    if {"S", "SS", "ST"} & set(types):
        d = p_t - p_t.mean(0)
        out["S"] = d
        if "SS" in types:
            d2 = d * d
            out["SS"] = torch.sub(d2, d2.sum(0), alpha=(n - 1) / n)
        if "ST" in types:
            out["ST"] = d * vel.sum(0) - (d * vel).sum(0)
    if "TS" in types:
        out["TS"] = vel * (p_tm1 - p_tm1.mean(0))
    if "TT" in types:
        out["TT"] = vel * (p_tm1 - p_tm2)
    factors = tuple(factor.get(k, 1.0) for k in types)
    if not types:
        return vel.new_zeros(0, *vel.shape), vel, factors
    return torch.stack([out[k] for k in types]), vel, factors


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
