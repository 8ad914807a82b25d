"""Vectorised meta-path features against a naive loop over pedestrians."""

from __future__ import annotations

import pytest
import torch

from crowdnav_mesrnn.graph import METAPATH_TYPES, metapath_features, metapath_features_step


def naive_features(p: torch.Tensor, m: torch.Tensor) -> dict[str, torch.Tensor]:
    """Direct transcription of the equations with loops; p (T, N, 2) float64, m (T, N) bool."""
    t_len, n, _ = p.shape
    out = {k: torch.zeros(t_len, n, 2, dtype=p.dtype) for k in METAPATH_TYPES}

    def vel(i: int, t: int) -> torch.Tensor:
        if t >= 1 and m[t, i] and m[t - 1, i]:
            return p[t, i] - p[t - 1, i]
        return torch.zeros(2, dtype=p.dtype)

    for t in range(t_len):
        for i in range(n):
            if not m[t, i]:
                continue
            out["T"][t, i] = vel(i, t)
            out["TT"][t, i] = vel(i, t) * (vel(i, t - 1) if t >= 1 else torch.zeros(2, dtype=p.dtype))
            for j in range(n):
                if j == i:
                    continue
                if m[t, j]:
                    dij = p[t, i] - p[t, j]
                    out["S"][t, i] += dij
                    out["ST"][t, i] += dij * vel(j, t)
                    for k in range(n):
                        if k in (i, j) or not m[t, k]:
                            continue
                        out["SS"][t, i] += dij * (p[t, j] - p[t, k])
                if t >= 1 and m[t - 1, j] and m[t - 1, i]:
                    out["TS"][t, i] += vel(i, t) * (p[t - 1, i] - p[t - 1, j])
    return out


@pytest.mark.parametrize("n", [1, 2, 5, 9])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_naive_loop(n: int, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    t_len = 6
    p = torch.randn(t_len, n, 2, generator=g, dtype=torch.float64) * 3
    m = torch.rand(t_len, n, generator=g) < 0.7
    m[2] = False  # a fully masked step
    # Garbage at absent positions must not leak into any feature.
    p = torch.where(m.unsqueeze(-1), p, torch.full_like(p, 1e6))
    got = metapath_features(p, m)
    want = naive_features(p, m)
    for k in METAPATH_TYPES:
        torch.testing.assert_close(got[k], want[k], msg=f"feature {k}")


def test_batched_leading_dims_and_dtypes() -> None:
    g = torch.Generator().manual_seed(3)
    p = torch.randn(2, 3, 5, 4, 2, generator=g, dtype=torch.float64)
    m = torch.rand(2, 3, 5, 4, generator=g) < 0.8
    batched = metapath_features(p, m)
    for a in range(2):
        for b in range(3):
            single = naive_features(p[a, b], m[a, b])
            for k in METAPATH_TYPES:
                torch.testing.assert_close(batched[k][a, b], single[k])
    f32 = metapath_features(p.float(), m)
    for k in METAPATH_TYPES:
        assert f32[k].dtype == torch.float32
        torch.testing.assert_close(f32[k].double(), batched[k], rtol=1e-4, atol=1e-4)


def test_temporal_terms_zero_at_start_and_single_pedestrian_spatial_zero() -> None:
    p = torch.randn(4, 1, 2)
    m = torch.ones(4, 1, dtype=torch.bool)
    f = metapath_features(p, m)
    assert torch.all(f["T"][0] == 0) and torch.all(f["TT"][:2] == 0)
    for k in ("S", "SS", "ST", "TS"):
        assert torch.all(f[k] == 0), k
    torch.testing.assert_close(f["T"][1:], p[1:] - p[:-1])


def test_step_kernel_matches_sequence_and_subset_types() -> None:
    g = torch.Generator().manual_seed(5)
    p = torch.randn(5, 6, 2, generator=g)
    m = torch.rand(5, 6, generator=g) < 0.8
    full = metapath_features(p, m)
    step = metapath_features_step(p[4], p[3], p[2], m[4], m[3], m[2], types=("S", "TT"))
    assert set(step) == {"S", "TT"}
    torch.testing.assert_close(step["S"], full["S"][4])
    torch.testing.assert_close(step["TT"], full["TT"][4])


def test_bad_shapes_and_types_raise() -> None:
    with pytest.raises(ValueError, match="positions must be"):
        metapath_features(torch.zeros(3, 4, 2), torch.ones(3, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="valid: S, T"):
        metapath_features(torch.zeros(3, 4, 2), torch.ones(3, 4, dtype=torch.bool), types=("XX",))
