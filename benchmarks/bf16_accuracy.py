"""Does bf16 autocast keep validation ADE within 1 % of fp32? Full training runs, several seeds each.

Run: ``python benchmarks/bf16_accuracy.py --model mesrnn --split univ --config configs/predictor/mesrnn.yaml``
(``--shard 0/2`` and ``--shard 1/2`` in two processes to use both cores; then once more without
``--shard`` to print the table). Trains ``--seeds`` seeds of one configuration in fp32 and in bf16
(``--set precision=bf16``) into ``--out`` (default ``runs/predictor/bf16/MODEL/SPLIT/CONFIG[-KEY=VALUE...]``);
finished runs are skipped and interrupted ones resume, as in ``predictor plan``, after a check that they were
trained with this configuration and seed. An fp32 run of the same configuration and
seed in ``--fp32-from`` (a folder template with ``{seed}``, e.g. a plan run) is used instead of training
it again. Prints each run's best validation ADE and training rate, the mean ± std per precision, and
the difference bf16 − fp32 with a t interval, as metres and as a fraction of fp32: paired by seed (a
seed fixes the initial weights and the data order in both precisions, so only the precision differs),
and unpaired (Welch) for reference. The 1 % criterion counts as shown only when the whole paired
interval lies below +1 %. The training rates come from each run's own epochs: runs made under
different loads do not compare; ``benchmarks/predictor_speed.py`` measures the rates like for like.

Validation ADE only (the ``_val`` pieces of the training scenes): test data are not read.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import yaml

from agents.stats import welch_seed_test
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.studies.plan import Candidate, Run, parse_shard, read_done, run_lock, train_run, yaml_scalar
from crowdnav_mesrnn.studies.plan_budget import epoch_rates


def default_out(model: str, split: str, config: str, sets: dict) -> Path:
    """``runs/predictor/bf16/MODEL/SPLIT/CONFIG[-KEY=VALUE...]``: one folder per configuration, so checks of
    different configurations never share runs."""
    name = Path(config.format(model=model)).stem + "".join(f"-{k}={yaml_scalar(v)}" for k, v in sorted(sets.items()))
    return Path("runs/predictor/bf16") / model / split / name


def runs_for(args: argparse.Namespace) -> dict[str, list[Run]]:
    sets = {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in args.set or [])}
    out = Path(args.out) if args.out else default_out(args.model, args.split, args.config, sets)
    runs: dict[str, list[Run]] = {}
    for precision in ("fp32", "bf16"):
        cand = Candidate(precision, args.config, {**sets, "precision": precision})
        runs[precision] = []
        for seed in args.seeds:
            folder = out / precision / f"seed{seed}"
            if precision == "fp32" and args.fp32_from:
                given = Path(args.fp32_from.format(seed=seed))
                if read_done(given) is not None:
                    folder = given
            if (folder / "run.yaml").is_file():  # a run to reuse or resume: it must be this configuration
                check_same_recipe(folder, args.model, cand, seed)
            runs[precision].append(Run("bf16-check", args.model, args.split, cand, seed, folder))
    return runs


def check_same_recipe(folder: Path, model: str, cand: Candidate, seed: int) -> None:
    """A reused fp32 run must have been trained with exactly this configuration and seed."""
    from crowdnav_mesrnn.training.trainer import load_configs

    recorded = yaml.safe_load((folder / "run.yaml").read_text())
    mcfg, tcfg = load_configs(model, cand.config_path(model), {**cand.overrides, "seed": seed})
    want = {"model": mcfg.to_dict(), "train": tcfg.__dict__}
    for part in ("model", "train"):
        for key, value in want[part].items():
            if key not in ("split", "data_dir") and recorded[part].get(key) != value:
                raise SystemExit(
                    f"{folder}/run.yaml: {part}.{key} is {recorded[part].get(key)!r}, this check trains with "
                    f"{value!r}; pass a matching --config/--set, another --out, or drop --fp32-from"
                )


def rate(folder: Path) -> float | None:
    """Mean training windows/s over the run's epochs."""
    rates = epoch_rates(folder)
    return float(np.mean(rates)) if rates else None


def report(runs: dict[str, list[Run]]) -> dict:
    vals: dict[str, dict[int, float]] = {}
    print(f"{'precision':<10}{'seed':>5}{'best val ADE m':>16}{'windows/s':>11}  folder")
    for precision, group in runs.items():
        vals[precision] = {}
        for run in group:
            done = read_done(run.out)
            ade = float(done["best_val_ade_m"]) if done else None
            r = rate(run.out)
            if ade is not None:
                vals[precision][run.seed] = ade
            print(
                f"{precision:<10}{run.seed:>5}{(f'{ade:.4f}' if ade is not None else 'not done'):>16}"
                f"{(f'{r:.1f}' if r else '–'):>11}  {run.out}"
            )
    out: dict = {"val_ade_m": vals}
    seeds = sorted(set(vals["bf16"]) & set(vals["fp32"]))
    if len(seeds) < 2:
        print("need at least two seeds finished in both precisions for an interval")
        return out
    a = np.array([vals["bf16"][k] for k in seeds])
    b = np.array([vals["fp32"][k] for k in seeds])
    ref = float(b.mean())
    print(f"seeds {seeds}: fp32 {ref:.4f} ± {b.std(ddof=1):.4f} m; bf16 {a.mean():.4f} ± {a.std(ddof=1):.4f} m")
    # Paired by seed (same initial weights and data order; only the precision differs): the design's test,
    # a one-sample t interval of the per-seed differences (against a fixed 0). Unpaired (Welch), for
    # reference: ignores that the seeds match.
    paired = welch_seed_test(a - b, [0.0])
    welch = welch_seed_test(a, b)
    for name, test in (("paired by seed", paired), ("Welch, unpaired", welch)):
        est, (lo, hi), df = test["difference"], test["difference_ci"], test["df"]
        print(
            f"bf16 − fp32, {name}: {est:+.4f} m [{lo:+.4f}, {hi:+.4f}] (t, df {df:.1f}) = "
            f"{100 * est / ref:+.2f} % [{100 * lo / ref:+.2f}, {100 * hi / ref:+.2f}] of fp32"
        )
        out[name] = {"diff_m": est, "ci_m": [lo, hi], "relative": [est / ref, lo / ref, hi / ref], "df": df}
    shown = bool(paired["difference_ci"][1] / ref < 0.01)  # False when there is no interval (nan)
    print(
        "within 1 % (paired interval below +1 %): "
        + ("shown" if shown else "not shown (the paired interval reaches +1 % or beyond)")
    )
    out["within_1_percent_shown"] = shown
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", choices=predictors.names(predictors.PRETRAINED, plugins=False), default="mesrnn")
    p.add_argument("--split", default="univ")
    p.add_argument("--config", default="configs/predictor/mesrnn.yaml", help="YAML (may contain {model})")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="extra model/train keys (YAML values)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--out", default=None)
    p.add_argument("--fp32-from", default=None, help="folder template with {seed} of finished fp32 runs to reuse")
    p.add_argument("--shard", default=None, help="i/n: train only every n-th run from the i-th (one per core)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None, help="also write the table's figures to this file")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    runs = runs_for(args)
    every = [r for group in runs.values() for r in group]
    shard = parse_shard(args.shard) if args.shard else (0, 1)
    for i, run in enumerate(every):
        if i % shard[1] != shard[0] or read_done(run.out) is not None:
            continue
        with run_lock(run.out) as held:
            if not held:
                print(f"{run.out}: being trained by another process; skipped")
                continue
            print(f"[{run.candidate.name} seed {run.seed}] -> {run.out}")
            train_run(run, data_dir=args.data_dir)
    result = report(runs)
    if args.json:
        from crowdnav_mesrnn.utils import atomic_write_text

        atomic_write_text(args.json, json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
