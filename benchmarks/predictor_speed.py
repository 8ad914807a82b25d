"""Training throughput and forecast latency of the structural RNN predictors, against the CPU's matmul peak.

Run: ``python benchmarks/predictor_speed.py [--quick] [--threads 1 2]``. Uses real ETH/UCY training
windows when ``$CROWDNAV_MESRNN_DATA`` is set (synthetic windows otherwise). Prints the matmul peak
measured in the same run (``torch.mm`` of 1024² matrices, fp32 and bf16, per thread count), training
throughputs with the fraction of that peak they reach (best of interleaved passes: on a shared machine
the least disturbed), latency medians, and ratios against the first implementation
(:mod:`crowdnav_mesrnn.models.reference`) run in the same process; never asserts on time.

FLOPs per training window are counted as in issue 10: every pedestrian of the window (scored and
context) at each of the 19 input steps, the multiply-adds of the node and edge LSTMs and embeddings,
x 2 (multiply + add) x 3 (forward + backward). The fast path computes only pedestrians present at a
step, so it executes less than this nominal count (the header says how much less).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
import torch
from _timing import matmul_peak_gflops, median_seconds

from crowdnav_mesrnn.data import MinMax, collate, data_available, split_windows
from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.evaluation.metrics import batches
from crowdnav_mesrnn.models.architecture import ModelConfig
from crowdnav_mesrnn.models.learned import LearnedPredictor
from crowdnav_mesrnn.models.pretrained import load_pretrained
from crowdnav_mesrnn.models.reference import reference_forward, reference_rollout
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
from crowdnav_mesrnn.training.trainer import keep_freed_memory, masked_loss

COMPACT = {"node_embed": 64, "node_hidden": 128, "edge_embed": 32, "edge_hidden": 64}
STEPS = OBS_LEN + PRED_LEN - 1


def synthetic_windows(count: int, rng: np.random.Generator) -> list:
    from crowdnav_mesrnn.data.windows import Window

    out = []
    for _ in range(count):
        n = int(rng.integers(4, 40))
        pos = np.cumsum(rng.normal(0, 0.3, (20, n, 2)), 0).astype(np.float32) + rng.uniform(0, 10, (1, n, 2))
        pres = rng.uniform(size=(20, n)) < 0.8
        out.append(Window(pos * pres[..., None], pres, pres.all(0), "synthetic", 0, np.arange(n)))
    return out


def macs_per_pedestrian_step(cfg: ModelConfig) -> int:
    """Multiply-adds of one pedestrian at one step (embeddings, LSTMs, decoder)."""
    k = len(cfg.types)
    node = 2 * cfg.node_embed + (cfg.node_embed + k * cfg.edge_hidden + cfg.node_hidden) * 4 * cfg.node_hidden
    edge = k * (2 * cfg.edge_embed + (cfg.edge_embed + cfg.edge_hidden) * 4 * cfg.edge_hidden)
    return node + edge + 2 * cfg.node_hidden


def trainer_pass(cfg: ModelConfig, bf16: bool = False, reference: bool = False):
    """A function running one training step (forward, loss, backward, clip, Adam) on a batch."""
    torch.manual_seed(0)
    net = StructuralRNN(cfg).train()
    opt = torch.optim.Adam(net.parameters(), 1e-3)

    def one(p: torch.Tensor, m: torch.Tensor) -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred, used = reference_forward(net, p, m, OBS_LEN) if reference else net(p, m, OBS_LEN)
        loss = masked_loss(pred.float(), used, p, m)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()

    return one


def train_rates(cfg: ModelConfig, data: list, repeats: int) -> dict[str, float]:
    """Windows/s of the fast path (fp32, bf16) and the first implementation, passes interleaved so
    that all three see the same load; the best pass of each (least disturbed)."""
    steps = {
        "fp32": trainer_pass(cfg),
        "bf16": trainer_pass(cfg, bf16=True),
        "first": trainer_pass(cfg, reference=True),
    }
    for one in steps.values():
        one(*data[0][:2])  # warm-up
    windows = sum(d[2] for d in data)
    best = dict.fromkeys(steps, 0.0)
    for _ in range(repeats):
        for name, one in steps.items():
            t0 = time.perf_counter()
            for p, m, _n in data:
                one(p, m)
            best[name] = max(best[name], windows / (time.perf_counter() - t0))
    return best


def training_batches(windows: list, norm: MinMax, batch_size: int, count: int) -> list:
    n_chunks = -(-len(windows) // batch_size)
    chunks = list(batches(windows, batch_size, np.random.default_rng(0).permutation(n_chunks)))[:count]
    out = []
    for chunk in chunks:
        pos, pres, _ = collate([windows[i] for i in chunk])
        p, m = torch.from_numpy(pos), torch.from_numpy(pres)
        out.append((torch.where(m.unsqueeze(-1), norm.normalise(p), torch.zeros_like(p)), m, len(chunk)))
    return out


class ScanIncremental:
    """The incremental forecast as it was before the online path (issue 19): one observed step and the rollout
    through the general :meth:`StructuralRNN.scan` (masks everywhere, separate input and recurrent products, the
    gathered rows' states copied), with states carried between calls; all ``n`` slots present."""

    def __init__(self, pred: LearnedPredictor, hist: np.ndarray) -> None:
        self.pred, self.net = pred, pred.net
        n = hist.shape[1]
        with torch.no_grad():
            x = pred.norm.normalise(torch.from_numpy(hist))[None]
        self.m = torch.ones(1, n, dtype=torch.bool)
        self.state = self.net.init_state(n)
        self.pos = [x[:, -2], x[:, -3]]
        self.x = x[:, -1]

    @torch.no_grad()
    def __call__(self) -> np.ndarray:
        net, m = self.net, self.m
        nxt, self.state = net.step((self.x, *self.pos), (m, m, m), self.state)
        rest, _, _ = net.scan(
            nxt.new_zeros(0, *nxt.shape),
            torch.zeros(0, *m.shape, dtype=torch.bool),
            (self.x, self.pos[0]),
            (m, m),
            dict(self.state),
            free_steps=self.pred.pred_len - 1,
            roll_mask=m,
            first_pred=nxt,
        )
        preds = torch.cat([nxt, rest[:, 0]], 0)
        return self.pred.norm.denormalise(preds).permute(1, 0, 2).numpy()


def with_random_head(pred: LearnedPredictor) -> LearnedPredictor:
    """The same weights with a distribution head (random head weights: the timing does not depend on them)."""
    net = StructuralRNN(ModelConfig.from_dict({**pred.net.cfg.to_dict(), "head": "gaussian"}))
    torch.manual_seed(0)
    head = {k: torch.randn_like(v) * 0.1 for k, v in net.state_dict().items() if k not in pred.net.state_dict()}
    net.load_state_dict({**pred.net.state_dict(), **head})
    return LearnedPredictor(net, pred.norm)


def latency_table(repeats: int, peak_fp32: float, models: list[str], sizes: list[int], cpu_time: bool = False) -> None:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    clock = time.process_time if cpu_time else time.perf_counter

    def median_ms(fn: Any) -> float:
        return median_seconds(fn, repeats, clock) * 1e3

    what = "CPU time of this process" if cpu_time else "wall time"
    print(f"\nForecast latency, shipped zara1 weights, 1 thread (ms of {what}, median of {repeats} calls):")
    print("  from scratch = LearnedPredictor.forecast: 8 observed steps + 12-step rollout;")
    print("  bf16         = the same under torch.autocast(bfloat16) (matmuls in bf16, states in fp32);")
    print("  scan incr.   = the incremental forecast before issue 19: one observed step + the rollout through the")
    print("                 general StructuralRNN.scan, states carried (today's path until then);")
    print("  online       = OnlineForecaster.observe (one step, carried states) + forecast (the online path);")
    print("  online+dist  = the same with a distribution head: observe + forecast_distribution (means, scales, rho);")
    print("  first impl.  = the same from-scratch rollout through crowdnav_mesrnn.models.reference;")
    print(
        f"  floor        = the from-scratch forecast's multiply-adds ({STEPS} steps) at the 1-thread fp32 matmul "
        f"peak ({peak_fp32:.0f} GFLOP/s):\n                 no fp32 implementation on one thread can be faster; "
        f"online floor: the same for the {PRED_LEN} steps of an incremental forecast"
    )
    print(
        f"{'model':<8}{'N':>5}{'from scratch':>14}{'bf16':>8}{'scan incr.':>12}{'online':>9}{'online+dist':>13}"
        f"{'first impl.':>13}{'online/scan':>13}{'floor':>8}{'online floor':>14}"
    )
    for model in models:
        pred = load_pretrained(model, "zara1")
        dist = with_random_head(pred)
        macs = macs_per_pedestrian_step(pred.net.cfg)
        for n in sizes:
            hist = (np.cumsum(rng.normal(0, 0.3, (8, n, 2)), 0) + 5).astype(np.float32)
            mask = np.ones((8, n), bool)
            scratch = median_ms(lambda h=hist, m=mask, p=pred: p.forecast(h, m))

            def scratch_bf16(h=hist, m=mask, p=pred) -> None:
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    p.forecast(h, m)

            bf16 = median_ms(scratch_bf16)
            scan_inc = median_ms(ScanIncremental(pred, hist))
            online, online_d = pred.online(n), dist.online(n)
            for t in range(8):
                online.observe(hist[t], mask[t])
                online_d.observe(hist[t], mask[t])

            def incremental(o=online, h=hist, m=mask) -> None:
                o.observe(h[-1], m[-1])
                o.forecast()

            def incremental_dist(o=online_d, h=hist, m=mask) -> None:
                o.observe(h[-1], m[-1])
                o.forecast_distribution()

            inc = median_ms(incremental)
            inc_d = median_ms(incremental_dist)
            x = pred.norm.normalise(torch.from_numpy(hist))[None]
            mt = torch.from_numpy(mask)[None]

            def first(net=pred.net, x=x, mt=mt) -> None:
                with torch.no_grad():
                    reference_rollout(net, x, mt, PRED_LEN)

            ref = median_ms(first)
            floor = n * STEPS * macs * 2 / (peak_fp32 * 1e9) * 1e3
            online_floor = n * PRED_LEN * macs * 2 / (peak_fp32 * 1e9) * 1e3
            print(
                f"{model:<8}{n:>5}{scratch:>14.2f}{bf16:>8.2f}{scan_inc:>12.2f}{inc:>9.2f}{inc_d:>13.2f}{ref:>13.2f}"
                f"{inc / scan_inc:>12.2f}x{floor:>8.2f}{online_floor:>14.2f}"
            )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer batches and repeats")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts for training")
    ap.add_argument("--skip-training", action="store_true")
    ap.add_argument("--latency-only", action="store_true", help="only the latency table (and the 1-thread peak)")
    ap.add_argument("--latency-repeats", type=int, default=None, help="calls per latency median (default 9/25)")
    ap.add_argument("--models", nargs="+", default=["mesrnn", "srnn", "vlstm"], help="models of the latency table")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 10, 50], help="pedestrians of the latency table")
    ap.add_argument("--cpu-time", action="store_true", help="latency in CPU time of this process instead of wall time")
    args = ap.parse_args()
    keep_freed_memory()  # as in training
    reps = 9 if args.quick else 25
    if args.latency_only:
        args.threads, args.skip_training = [1], True
    peaks = {}
    print("Matmul peak: torch.mm of 1024 x 1024 matrices (GFLOP/s, best of repeats)")
    print(f"{'threads':>7}{'fp32':>9}{'bf16':>9}")
    for th in args.threads:
        peaks[th] = {dt: matmul_peak_gflops(dt, th, reps) for dt in (torch.float32, torch.bfloat16)}
        print(f"{th:>7}{peaks[th][torch.float32]:>9.0f}{peaks[th][torch.bfloat16]:>9.0f}")
    if not args.skip_training:
        if data_available():
            windows = split_windows("zara1", "train", min_scored=2)
            source = (
                f"zara1 train windows (mean {np.mean([w.num_peds for w in windows]):.1f} pedestrians incl. context)"
            )
        else:
            windows = synthetic_windows(512, np.random.default_rng(0))
            source = "synthetic windows (no ETH/UCY data found)"
        norm = MinMax.fit(np.concatenate([w.positions[w.present] for w in windows]))
        data = training_batches(windows, norm, 32, 3 if args.quick else 8)
        present = sum(int(d[1][:, :STEPS].sum()) for d in data)  # pedestrian-steps computed
        real = sum(int(d[1].any(1).sum()) for d in data)  # pedestrians of the windows (no padding)
        nominal_peds = real / sum(d[2] for d in data)
        repeats = 2 if args.quick else 3
        for th in args.threads:
            torch.set_num_threads(th)
            print(
                f"\nTraining throughput, {source}: {len(data)} batches of 32 (bucketed by size), teacher forcing, "
                f"Adam step included, {th} thread(s), best of {repeats} interleaved passes.\n"
                f"% peak = nominal GFLOP/s ({nominal_peds:.1f} pedestrians x {STEPS} steps per window) over the "
                f"matmul peak;\nthe fast path computes only present pedestrians: "
                f"{present / (real * STEPS):.0%} of that nominal work."
            )
            rows = []
            for model in ("mesrnn", "srnn", "vlstm"):
                for label, kw in (("paper", {}), ("compact", COMPACT)):
                    cfg = ModelConfig(model=model, **kw)
                    gflop = nominal_peds * STEPS * macs_per_pedestrian_step(cfg) * 6 / 1e9
                    rows.append((model, label, gflop, train_rates(cfg, data, repeats)))
            for dt in (torch.float32, torch.bfloat16):  # the peak again after the load of this section
                peaks[th][dt] = max(peaks[th][dt], matmul_peak_gflops(dt, th, reps))
            print(
                f"matmul peak (best of the measurements before and after): fp32 {peaks[th][torch.float32]:.0f}, "
                f"bf16 {peaks[th][torch.bfloat16]:.0f} GFLOP/s"
            )
            print(
                f"{'model':<8}{'sizes':<9}{'windows/s':>10}{'% fp32 peak':>13}{'bf16 windows/s':>16}"
                f"{'% bf16 peak':>13}{'first impl.':>13}{'speed-up':>10}"
            )
            for model, label, gflop, r in rows:
                print(
                    f"{model:<8}{label:<9}{r['fp32']:>10.1f}{100 * r['fp32'] * gflop / peaks[th][torch.float32]:>12.0f}%"
                    f"{r['bf16']:>16.1f}{100 * r['bf16'] * gflop / peaks[th][torch.bfloat16]:>12.0f}%"
                    f"{r['first']:>13.1f}{r['fp32'] / r['first']:>9.1f}x"
                )
    if 1 not in peaks:
        peaks[1] = {torch.float32: matmul_peak_gflops(torch.float32, 1, reps)}
    latency_table(
        args.latency_repeats or (9 if args.quick else 25),
        peaks[1][torch.float32],
        args.models,
        args.sizes,
        args.cpu_time,
    )


if __name__ == "__main__":
    main()
