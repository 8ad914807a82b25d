"""The incremental forecast of this checkout against the same code at another git revision, alternating.

Run: ``python benchmarks/online_ab.py --against 5a04669 [--pairs 6] [--repeats 40] [--pedestrians 50]
[--head gaussian]``.

One process per measurement and revision, the two revisions alternating ``--pairs`` times, so both see the
same load (on a shared machine single figures move by tens of percent between minutes; alternating pairs
compare like with like). Each process times ``OnlineForecaster.observe`` (one step, carried states) +
``forecast`` of the shipped zara1 MESRNN for N pedestrians (random walks, everyone present), one thread (with
``--head gaussian``: the shipped distribution head and ``forecast_distribution``, means, scales and correlations), and
prints the median wall time, the median CPU time of the process and the fastest call over ``--repeats`` calls.
The other revision is exported with ``git archive`` into a temporary folder and imported from there
(``PYTHONPATH``), with the same shipped weights. Prints every pair, the medians over pairs, and the median of the
per-pair ratios; never asserts on time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

CHILD = r"""
import json, statistics, sys, time
import numpy as np, torch
torch.set_num_threads(1)
from crowdnav_mesrnn import load_pretrained
n, repeats, head = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
pred = load_pretrained("mesrnn", "zara1", head=head)
rng = np.random.default_rng(0)
hist = (np.cumsum(rng.normal(0, 0.3, (8, n, 2)), 0) + 5).astype(np.float32)
mask = np.ones((8, n), bool)
online = pred.online(n)
for t in range(8):
    online.observe(hist[t], mask[t])
def call():
    online.observe(hist[-1], mask[-1])
    online.forecast() if head == "point" else online.forecast_distribution()
for _ in range(3):
    call()
wall, cpu = [], []
for _ in range(repeats):
    w0, c0 = time.perf_counter(), time.process_time()
    call()
    cpu.append(time.process_time() - c0)
    wall.append(time.perf_counter() - w0)
print(json.dumps({"wall_ms": statistics.median(wall) * 1e3, "cpu_ms": statistics.median(cpu) * 1e3,
                  "min_ms": min(wall) * 1e3}))
"""


def measure(root: Path, n: int, repeats: int, head: str) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(n), str(repeats), head], cwd=root, env=env, capture_output=True, text=True
    )
    if out.returncode:
        raise RuntimeError(f"measurement in {root} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", required=True, help="git revision to compare with (e.g. 5a04669)")
    ap.add_argument("--pairs", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--pedestrians", type=int, default=50)
    ap.add_argument(
        "--head",
        choices=["point", "gaussian"],
        default="point",
        help="gaussian: the distribution head (both revisions)",
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="online-ab-") as tmp:
        archive = subprocess.run(["git", "archive", args.against], cwd=REPO, capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", tmp], input=archive.stdout, check=True)
        rows = []
        print(
            f"incremental forecast, shipped zara1 MESRNN ({args.head} head), {args.pedestrians} pedestrians, 1 thread, "
            f"median of {args.repeats} calls (ms): this checkout vs {args.against}"
        )
        print(f"{'pair':>4}{'wall':>9}{'cpu':>9}{'min':>9}{'wall':>11}{'cpu':>9}{'min':>9}{'cpu ratio':>11}")
        for k in range(args.pairs):
            new = measure(REPO, args.pedestrians, args.repeats, args.head)
            old = measure(Path(tmp), args.pedestrians, args.repeats, args.head)
            rows.append((new, old))
            print(
                f"{k:>4}{new['wall_ms']:>9.2f}{new['cpu_ms']:>9.2f}{new['min_ms']:>9.2f}"
                f"{old['wall_ms']:>11.2f}{old['cpu_ms']:>9.2f}{old['min_ms']:>9.2f}{new['cpu_ms'] / old['cpu_ms']:>10.2f}x"
            )
    med = {
        side: {key: statistics.median(r[i][key] for r in rows) for key in rows[0][0]}
        for i, side in enumerate(("new", "old"))
    }
    ratio = statistics.median(r[0]["cpu_ms"] / r[1]["cpu_ms"] for r in rows)
    print(
        f"medians over pairs: this checkout wall {med['new']['wall_ms']:.2f}, cpu {med['new']['cpu_ms']:.2f}, "
        f"min {med['new']['min_ms']:.2f}; {args.against} wall {med['old']['wall_ms']:.2f}, cpu "
        f"{med['old']['cpu_ms']:.2f}, min {med['old']['min_ms']:.2f}; median CPU-time ratio {ratio:.2f}x"
    )


if __name__ == "__main__":
    main()
