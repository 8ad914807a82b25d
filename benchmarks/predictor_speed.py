"""Training throughput and forecast latency of the structural RNN predictors.

Run: ``python benchmarks/predictor_speed.py [--quick]``. Uses real ETH/UCY training windows when
``$CROWDNAV_MESRNN_DATA`` is set (synthetic windows otherwise). Prints medians of repeats and ratios
against a reference run in the same process (one window per optimiser step, the authors' style);
never asserts on time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _timing import median_seconds

from crowdnav_mesrnn.data import MinMax, collate, data_available, split_windows
from crowdnav_mesrnn.data.constants import OBS_LEN
from crowdnav_mesrnn.evaluation import batches
from crowdnav_mesrnn.models.learned import LearnedPredictor
from crowdnav_mesrnn.models.structural_rnn import ModelConfig, StructuralRNN
from crowdnav_mesrnn.training import masked_loss

COMPACT = {"node_embed": 64, "node_hidden": 128, "edge_embed": 32, "edge_hidden": 64}


def synthetic_windows(count: int, rng: np.random.Generator) -> list:
    from crowdnav_mesrnn.data.windows import Window

    out = []
    for _ in range(count):
        n = int(rng.integers(4, 40))
        pos = np.cumsum(rng.normal(0, 0.3, (20, n, 2)), 0).astype(np.float32) + rng.uniform(0, 10, (1, n, 2))
        pres = rng.uniform(size=(20, n)) < 0.8
        out.append(Window(pos * pres[..., None], pres, pres.all(0), "synthetic", 0, np.arange(n)))
    return out


def train_rate(cfg: ModelConfig, windows: list, norm: MinMax, batch_size: int, max_batches: int) -> float:
    torch.manual_seed(0)
    net = StructuralRNN(cfg).train()
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    n_chunks = -(-len(windows) // batch_size)
    chunks = list(batches(windows, batch_size, np.random.default_rng(0).permutation(n_chunks)))[:max_batches]
    seen, t0 = 0, time.perf_counter()
    for chunk in chunks:
        pos, pres, _ = collate([windows[i] for i in chunk])
        p, m = torch.from_numpy(pos), torch.from_numpy(pres)
        p = torch.where(m.unsqueeze(-1), norm.normalise(p), torch.zeros_like(p))
        pred, used = net(p, m, OBS_LEN)
        loss = masked_loss(pred, used, p, m)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
        seen += len(chunk)
    return seen / (time.perf_counter() - t0)


def median_ms(fn, repeats: int) -> float:
    return median_seconds(fn, repeats) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer batches and repeats")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    if data_available():
        windows = split_windows("zara1", "train", min_scored=2)
        source = f"zara1 train windows ({len(windows)}, mean {np.mean([w.num_peds for w in windows]):.1f} pedestrians incl. context)"
    else:
        windows = synthetic_windows(512, rng)
        source = "synthetic windows (no ETH/UCY data found)"
    norm = MinMax.fit(np.concatenate([w.positions[w.present] for w in windows]))
    nb = 4 if args.quick else 12
    print(f"Training throughput on {source}, {args.threads} thread(s), batch 32, bucketed by size")
    print(f"{'model':<8}{'sizes':<10}{'windows/s':>11}{'1 window/step':>15}{'batching speed-up':>19}")
    for model in ("mesrnn", "srnn", "vlstm"):
        for label, kw in (("paper", {}), ("compact", COMPACT)):
            cfg = ModelConfig(model=model, **kw)
            rate = train_rate(cfg, windows, norm, 32, nb)
            ref = train_rate(cfg, windows, norm, 1, nb * 2)
            print(f"{model:<8}{label:<10}{rate:>11.1f}{ref:>15.1f}{rate / ref:>18.1f}x")

    print("\nForecast latency (ms, median): from scratch = 8 observed steps + 12-step rollout;")
    print("incremental = one observed step with carried hidden states + 12-step rollout")
    print(f"{'model':<8}{'N':>5}{'from scratch':>14}{'incremental':>13}{'ratio':>8}")
    reps = 5 if args.quick else 20
    for model in ("mesrnn", "srnn", "vlstm"):
        torch.manual_seed(0)
        pred = LearnedPredictor(StructuralRNN(ModelConfig(model=model)), norm)
        for n in (1, 10, 50, 100):
            hist = (np.cumsum(rng.normal(0, 0.3, (8, n, 2)), 0) + 5).astype(np.float32)
            mask = np.ones((8, n), bool)
            scratch = median_ms(lambda h=hist, m=mask, p=pred: p.forecast(h, m), reps)
            online = pred.online(n)
            for t in range(8):
                online.observe(hist[t], mask[t])

            def incremental(o=online, h=hist, m=mask) -> None:
                o.observe(h[-1], m[-1])
                o.forecast()

            inc = median_ms(incremental, reps)
            print(f"{model:<8}{n:>5}{scratch:>14.2f}{inc:>13.2f}{scratch / inc:>7.1f}x")


if __name__ == "__main__":
    main()
