"""Cost of the vectorised meta-path features against N, and against a naive loop.

Run: ``python benchmarks/metapath_speed.py``. Prints medians of repeats; never asserts on time.
"""

from __future__ import annotations

import torch
from _timing import median_seconds

from crowdnav_mesrnn.graph import METAPATH_TYPES, metapath_features


def naive(p: torch.Tensor, m: torch.Tensor) -> None:
    """Per-pedestrian Python loops (the authors' style), only S, SS and T kinds of work."""
    t_len, n, _ = p.shape
    for t in range(t_len):
        for i in range(n):
            if not m[t, i]:
                continue
            acc = torch.zeros(2)
            for j in range(n):
                if j != i and m[t, j]:
                    dij = p[t, i] - p[t, j]
                    acc += dij
                    for k in range(n):
                        if k not in (i, j) and m[t, k]:
                            acc += dij * (p[t, j] - p[t, k])


def main() -> None:
    torch.set_num_threads(1)
    t_len = 20
    print(f"meta-path features {', '.join(METAPATH_TYPES)} for one {t_len}-step window, float32, 1 thread")
    print(f"{'N':>5}{'vectorised ms':>16}{'naive ms':>12}{'speed-up':>10}")
    for n in (1, 2, 5, 10, 20, 50, 100):
        p = torch.randn(t_len, n, 2)
        m = torch.rand(t_len, n) < 0.9
        vec = median_seconds(lambda p=p, m=m: metapath_features(p, m), 20)
        if n <= 10:
            slow = median_seconds(lambda p=p, m=m: naive(p, m), 3)
            print(f"{n:>5}{vec * 1e3:>16.3f}{slow * 1e3:>12.1f}{slow / vec:>9.0f}x")
        else:
            print(f"{n:>5}{vec * 1e3:>16.3f}{'-':>12}{'-':>10}")
    b, n = 64, 30
    p = torch.randn(b, t_len, n, 2)
    m = torch.rand(b, t_len, n) < 0.7
    vec = median_seconds(lambda: metapath_features(p, m), 10)
    print(f"batch of {b} windows x {n} pedestrians: {vec * 1e3:.2f} ms ({b / vec:.0f} windows/s)")


if __name__ == "__main__":
    main()
