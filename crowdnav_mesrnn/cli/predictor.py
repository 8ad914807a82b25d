"""``crowdnav-mesrnn predictor ...``: train, evaluate, export and plot trajectory predictors.

Each action adds its parser in an ``_add_<action>`` function and runs through a handler that imports what it needs
when called, so ``--help`` imports neither torch nor the modules behind the actions.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import existing_config
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_HELP

#: The shipped structural RNNs (weights per split), as the registry lists them.
LEARNED_MODELS: tuple[str, ...] = predictors.names(predictors.PRETRAINED, plugins=False)
#: The kinds of shipped predictor ``evaluate`` and ``calibrate`` take, and how their help describes each.
_MODEL_KINDS: dict[str, str] = {
    predictors.BASELINE: "a point forecast, no parameters",
    predictors.FITTED_BASELINE: "constant velocity with a Gaussian of scale a + b*h, parameters fitted per split",
    predictors.PRETRAINED: "structural RNNs, shipped weights per split",
}
#: Every shipped predictor, as the registry lists them: constant velocity, cv_gaussian and :data:`LEARNED_MODELS`.
MODELS: tuple[str, ...] = predictors.names(*_MODEL_KINDS, plugins=False)
#: The shipped predictors with a distribution without choosing a head (``cv_gaussian``).
DISTRIBUTION_BASELINES: tuple[str, ...] = predictors.names(predictors.FITTED_BASELINE, plugins=False)


def _models_help(lead: str) -> str:
    """``lead`` and the shipped predictors grouped by kind, from the registry."""
    groups = [f"{', '.join(predictors.names(k, plugins=False))} ({text})" for k, text in _MODEL_KINDS.items()]
    return f"{lead}: {'; '.join(groups)}"


def _check_checkpoint(args: argparse.Namespace) -> None:
    """``--checkpoint`` holds structural RNN weights: refuse it for a predictor without them."""
    if args.checkpoint and args.model not in LEARNED_MODELS:
        raise ValueError(
            f"--checkpoint holds the weights of a structural RNN ({', '.join(LEARNED_MODELS)}); {args.model!r} has none"
        )


def _parse_sets(items: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        out[key.strip()] = yaml.safe_load(value)
    return out


def _train(args: argparse.Namespace) -> int:
    if args.config is not None:  # a missing file is named before torch is imported
        existing_config(args.config, "predictor")
    import torch

    from crowdnav_mesrnn.training.trainer import Trainer, load_configs

    torch.set_num_threads(args.threads)
    overrides = _parse_sets(args.set)
    overrides["split"] = args.split
    if args.epochs is not None:
        overrides["epochs"] = args.epochs
    if args.data_dir:
        overrides["data_dir"] = args.data_dir
    mcfg, tcfg = load_configs(args.model, args.config, overrides)
    out = Path(args.out or f"runs/predictor/{args.model}_{args.split}")
    trainer = Trainer(mcfg, tcfg, out)
    if args.resume:
        trainer.resume()
        print(f"resumed {out / 'last.pt'} at epoch {trainer.epoch}")
    elif (out / "last.pt").exists():
        raise ValueError(f"{out / 'last.pt'} exists: pass --resume to continue it or --out for a new run")
    out.mkdir(parents=True, exist_ok=True)
    from crowdnav_mesrnn.utils import atomic_write_text

    atomic_write_text(
        out / "run.yaml",
        yaml.safe_dump(
            {"command": " ".join(sys.argv), "model": mcfg.to_dict(), "train": tcfg.__dict__}, sort_keys=False
        ),
    )
    print(
        f"training {args.model} on split {args.split}: {len(trainer.train_windows)} train / "
        f"{len(trainer.val_windows)} val windows -> {out}"
    )
    res = trainer.fit(progress=not args.no_progress, tensorboard=args.tensorboard)
    if res["select_on"] == "nll":
        print(f"best val NLL {res['best_val_nll_m']:.3f} (ADE {res['best_val_ade_m']:.3f} m); checkpoints in {out}")
    else:
        print(f"best val ADE {res['best_val_ade_m']:.3f} m; checkpoints in {out}")
    return 0


def _check_checkpoints(args: argparse.Namespace) -> None:
    """Refuse a ``--checkpoint`` for a predictor without weights, or one that names no file for one of the splits,
    before torch is imported."""
    if not args.checkpoint:
        return
    _check_checkpoint(args)
    for split in SPLITS if args.split == "all" else (args.split,):
        path = Path(args.checkpoint.format(split=split, model=args.model))
        if not path.is_file():
            raise FileNotFoundError(f"no predictor checkpoint at {path}")


def _checkpoint_loader(args: argparse.Namespace) -> Any:
    """``split -> LearnedPredictor`` from ``--checkpoint`` (a path that may hold ``{split}`` and ``{model}``), or None."""
    if not args.checkpoint:
        return None
    from crowdnav_mesrnn.models.learned import load_predictor

    template = args.checkpoint

    def load(split: str) -> Any:
        return load_predictor(template.format(split=split, model=args.model), model=args.model, split=split)

    return load


def _eval(args: argparse.Namespace) -> int:
    if args.versus and args.checkpoint:
        raise ValueError("--versus compares shipped weights; it takes no --checkpoint")
    _check_checkpoints(args)
    import torch

    from crowdnav_mesrnn.evaluation.protocol import evaluate_model, evaluate_versus, format_result

    torch.set_num_threads(args.threads)
    _check_checkpoint(args)
    head = args.head or ("gaussian" if args.samples else "point")
    common: dict[str, Any] = {
        "data_dir": args.data_dir,
        "part": args.part,
        "samples": args.samples,
        "sampling": args.sampling,
        "seed": args.seed,
        "head": head if args.model != "cv" else "point",
        "block_len": args.block_len,
        "n_resamples": args.resamples,
    }
    if args.versus:
        result = evaluate_versus(args.model, args.versus, splits=args.split, **common)
    else:
        result = evaluate_model(args.model, args.split, checkpoint_for=_checkpoint_loader(args), **common)
    return _emit(args, result, format_result)


def _emit(args: argparse.Namespace, result: dict[str, Any], fmt: Callable[[dict[str, Any]], str]) -> int:
    """Write ``result`` to ``--out`` (atomically) when given, and print it as JSON (``--json``) or as ``fmt``'s table."""
    if args.out:
        from crowdnav_mesrnn.utils import atomic_write_json

        atomic_write_json(args.out, result)
    print(json.dumps(result, indent=2) if args.json else fmt(result))
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    _check_checkpoints(args)
    import torch

    from crowdnav_mesrnn.uncertainty.calibration import calibrate_model, format_calibration

    torch.set_num_threads(args.threads)
    _check_checkpoint(args)
    predictor_for = _checkpoint_loader(args)
    result = calibrate_model(
        args.model,
        args.split,
        score=args.score,
        head=args.head if args.model != "cv" else "point",
        levels=args.levels,
        data_dir=args.data_dir,
        predictor_for=predictor_for,
        block_len=args.block_len,
        n_resamples=args.resamples,
        method=args.method,
        reveal=args.reveal,
        gamma_rule=args.gamma,
    )
    return _emit(args, result, format_calibration)


def _fit_head(args: argparse.Namespace) -> int:
    import torch

    from crowdnav_mesrnn.evaluation.protocol import resolve_splits
    from crowdnav_mesrnn.models.pretrained import pretrained_path
    from crowdnav_mesrnn.training.head_fit import HeadFitConfig, fit_head

    torch.set_num_threads(args.threads)
    cfg = HeadFitConfig(
        max_epochs=args.epochs,
        patience=args.patience,
        whiten_floor=args.whiten_floor,
        data_dir=args.data_dir,
        max_windows=args.max_windows,
    )
    jobs = []
    for split in resolve_splits(args.split):
        src = (
            Path(args.point.format(model=args.model, split=split)) if args.point else pretrained_path(args.model, split)
        )
        dest = (
            Path(args.out.format(model=args.model, split=split))
            if args.out
            else pretrained_path(args.model, split, "gaussian")
        )
        if not src.is_file():
            raise FileNotFoundError(
                f"no point weights for {args.model}/{split} at {src}: fit-head fits the head on them (train them with "
                f"`crowdnav-mesrnn predictor train --model {args.model} --split {split}`, then `predictor export`)"
            )
        if dest.exists() and not args.force:
            raise ValueError(f"{dest} exists: pass --force to replace it")
        jobs.append((split, src, dest))
    for split, src, dest in jobs:
        fit_head(src, dest, cfg, model=args.model, split=split, command=" ".join(sys.argv))
    return 0


def _fit_cv_gaussian(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.models import cv_gaussian_fit
    from crowdnav_mesrnn.models.cv_gaussian import PARAMS_DIR, params_path

    out_dir = Path(args.out_dir) if args.out_dir else PARAMS_DIR
    splits = list(SPLITS) if args.split == "all" else [args.split]
    held = [p for p in (params_path(s, out_dir) for s in splits) if p.exists()]
    if held and not args.force:
        raise ValueError(f"{held[0]} exists: pass --force to replace it (or --out-dir for another folder)")
    argv = ["--split", args.split, "--out-dir", str(out_dir)]
    return cv_gaussian_fit.main([*argv, *(["--data-dir", args.data_dir] if args.data_dir else [])])


def _export(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.models.pretrained import export_checkpoint

    path = export_checkpoint(args.checkpoint, args.model, args.split, args.note)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


def _select(args: argparse.Namespace) -> int:
    import torch

    from crowdnav_mesrnn.models.pretrained import export_checkpoint

    candidates = []
    for run in args.runs:
        best = Path(run) / "best.pt"
        if not best.is_file():
            print(f"skipping {run}: no best.pt", file=sys.stderr)
            continue
        ck = torch.load(best, map_location="cpu", weights_only=True)
        if ck["model_config"]["model"] != args.model or ck["train_config"]["split"] != args.split:
            raise ValueError(
                f"{best} is {ck['model_config']['model']}/{ck['train_config']['split']}, not {args.model}/{args.split}"
            )
        candidates.append((float(ck["best_val_ade_m"]), run, int(ck["epoch"])))
    if not candidates:
        raise ValueError("no candidate run has a best.pt")
    candidates.sort()
    val, run, epoch = candidates[0]
    note = f"lowest val ADE {val:.3f} m (epoch {epoch}) of: " + "; ".join(
        f"{Path(r).name} {v:.3f} m" for v, r, _ in candidates
    )
    path = export_checkpoint(Path(run) / "best.pt", args.model, args.split, note)
    print(f"{args.model}/{args.split}: {note}\nwrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


def _report(args: argparse.Namespace) -> int:
    import torch

    from crowdnav_mesrnn.studies.report import build_plan_report, build_report
    from crowdnav_mesrnn.studies.report_render import render, render_plan
    from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text

    if args.plan_only and args.out is None:
        print(
            "error: --plan-only needs --out (the default is the main page, docs/results/predictors.md)", file=sys.stderr
        )
        return 2
    out = Path(args.out or "docs/results/predictors.md")
    if args.render_only:
        source = out.with_suffix(".json")
        if not source.is_file():
            print(f"error: --render-only needs {source} from an earlier report", file=sys.stderr)
            return 2
        saved = json.loads(source.read_text())
        atomic_write_text(out, (render_plan if saved.get("plan_only") else render)(saved))
        print(f"wrote {out} from {source} (nothing re-evaluated)")
        return 0
    torch.set_num_threads(args.threads)
    if args.claims:
        return _report_claims(args, out)
    if args.plan_only:
        if args.plan is None or args.extra:
            print("error: --plan-only needs --plan and takes no --extra rows", file=sys.stderr)
            return 2
        text, results = build_plan_report(args.plan, args.data_dir, args.block_len, args.resamples)
    else:
        extra = dict(item.split("=", 1) for item in (args.extra or []))
        text, results = build_report(
            extra, data_dir=args.data_dir, plan=args.plan, block_len=args.block_len, n_resamples=args.resamples
        )
    atomic_write_text(out, text)
    atomic_write_json(out.with_suffix(".json"), results)
    print(text)
    print(f"wrote {out} and {out.with_suffix('.json')}")
    return 0


def _report_claims(args: argparse.Namespace, out: Path) -> int:
    """``report --claims``: test the paper's further claims and merge them into the page's JSON (every
    other key kept), then re-render the page. The plan's seeds are used where its run folders hold them
    all (``--plan``, else the plan the page was made with), else the shipped weights."""
    from crowdnav_mesrnn.studies.claims.compute import compute_claims
    from crowdnav_mesrnn.studies.report import add_claims
    from crowdnav_mesrnn.studies.report_render import render
    from crowdnav_mesrnn.utils import atomic_write_json, atomic_write_text

    source = out.with_suffix(".json")
    if args.plan_only or args.extra or args.render_only:
        print("error: --claims takes no --plan-only, --extra or --render-only", file=sys.stderr)
        return 2
    if not source.is_file():
        print(f"error: --claims adds to an existing page: {source} not found (run the whole report)", file=sys.stderr)
        return 2
    saved = json.loads(source.read_text())
    plan = args.plan or (saved.get("seeds") or {}).get("plan")
    claims = compute_claims(args.data_dir, plan, args.block_len, args.resamples, headline=saved)
    merged = add_claims(saved, claims)
    atomic_write_json(source, merged)
    atomic_write_text(out, render(merged))
    print(f"wrote {out} and {source} (claims added; every other key kept)")
    return 0


def main_plan(args: argparse.Namespace) -> int:
    """``crowdnav-mesrnn predictor plan``: run a stage of a comparison plan, or print its budget (``--dry-run``)."""
    existing_config(args.file, "predictor")  # a missing plan file is named before torch is imported
    import torch

    from crowdnav_mesrnn.studies.plan import execute, load_plan, parse_shard
    from crowdnav_mesrnn.studies.plan_budget import dry_run

    torch.set_num_threads(args.threads)
    plan = load_plan(args.file)
    if args.dry_run:
        print(
            dry_run(
                plan,
                args.stage if args.stage != "export" else "all",
                args.measure_batches,
                args.remeasure,
                args.data_dir,
            )
        )
        return 0
    execute(plan, args.stage, parse_shard(args.shard), args.data_dir, log=lambda s: print(s, flush=True))
    return 0


def _plot(args: argparse.Namespace) -> int:
    from crowdnav_mesrnn.studies.plotting import plot_window

    path = plot_window(args.split, args.window, args.out, models=args.models.split(","), data_dir=args.data_dir)
    print(f"wrote {path}")
    return 0


def _add_bootstrap_and_runtime(p: argparse.ArgumentParser) -> None:
    """The options every command with block-bootstrap intervals shares: the bootstrap, the data, the threads."""
    p.add_argument("--block-len", type=int, default=20, help="block bootstrap block length in windows (default 20)")
    p.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples (default 10000)")
    p.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")


def _add_train(psub: Any) -> None:
    """``predictor train``."""
    t = psub.add_parser("train", help="train a structural RNN on a split's train part (val for selection)")
    t.add_argument("--model", required=True, choices=LEARNED_MODELS, help="which structural RNN")
    t.add_argument("--split", required=True, choices=SPLITS, help="leave-one-out split: trained without its test scene")
    t.add_argument("--config", default=None, help="YAML with model: and train: (default configs/predictor/MODEL.yaml)")
    t.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a model or train key")
    t.add_argument("--epochs", type=int, default=None, help="epochs (default: the config's train.epochs)")
    t.add_argument("--out", default=None, help="run folder (default runs/predictor/MODEL_SPLIT)")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from last.pt")
    t.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    t.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    t.add_argument("--tensorboard", action="store_true", help="log to RUN/tb (needs the tb extra)")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(func=_train)


def _add_evaluate(psub: Any) -> None:
    """``predictor evaluate`` (alias ``eval``)."""
    e = psub.add_parser(
        "evaluate",
        aliases=["eval"],
        help="ADE/FDE on the test parts with a true autoregressive rollout (alias: eval)",
        description="ADE/FDE of a shipped predictor or a checkpoint on the leave-one-out test (or val) parts; with "
        "--samples K, a distribution's scores: NLL, energy score, best-of-K ADE/FDE per pedestrian and per scene "
        "(Social-GAN's) and the calibrated coverage of its 90 % regions, with paired block-bootstrap intervals "
        "against other predictors (--versus). Any predictor plug-in: crowdnav-mesrnn bench PREDICTOR --no-planner.",
    )
    e.add_argument(
        "--model", required=True, choices=MODELS, help=_models_help("which predictor (shipped unless --checkpoint)")
    )
    e.add_argument("--split", default="all", choices=(*SPLITS, "all"), help="split(s) to score (default: all)")
    e.add_argument("--part", default="test", choices=("test", "val"), help="part of the split (default: test)")
    e.add_argument("--checkpoint", default=None, help="checkpoint path; may contain {split} and {model}")
    e.add_argument("--json", action="store_true", help="print the result as one JSON object")
    e.add_argument("--out", default=None, help="also write the JSON result here (atomically)")
    e.add_argument(
        "--samples",
        type=int,
        default=0,
        help=f"with a distribution ({', '.join(DISTRIBUTION_BASELINES)}, or the gaussian head of "
        f"{', '.join(LEARNED_MODELS)}), draw K sampled futures per pedestrian and report best-of-K ADE/FDE per "
        "pedestrian (min_ade_m, min_fde_m) and per scene (scene_min_ade_m, scene_min_fde_m: in each window the "
        "sample with the smallest error summed over its pedestrians, Social-GAN's), the energy score of the 12-step "
        "future (energy_m, K >= 2) and, on test, the coverage of the 90 %% regions calibrated on validation "
        "(coverage_90), each with block-bootstrap intervals; implies --head gaussian for shipped weights (default 0: "
        "none)",
    )
    e.add_argument(
        "--sampling",
        default="coherent",
        choices=("marginal", "coherent", "feedback"),
        help="coherent (the default): each step drawn from its Gaussian of the mean rollout, one standard normal "
        "draw per sample and pedestrian shared by all 12 steps; marginal: an independent draw per step "
        "(Social-STGCNN's protocol); feedback: every draw fed back as the next input (structural RNNs only)",
    )
    e.add_argument("--seed", type=int, default=0, help="seed of the samples (default 0)")
    e.add_argument(
        "--head",
        default=None,
        choices=("point", "gaussian"),
        help=f"which shipped weights of {', '.join(LEARNED_MODELS)} (default point; gaussian with --samples); a "
        f"distribution also gets nll_m ({', '.join(DISTRIBUTION_BASELINES)} always has one)",
    )
    e.add_argument(
        "--versus",
        nargs="+",
        default=None,
        choices=MODELS,
        metavar="MODEL",
        help="also evaluate these shipped predictors with the same head, samples, sampling and seed, and give the "
        "paired differences (--model minus each) of ADE/FDE and every distribution score with block-bootstrap "
        f"intervals (the JSON's versus key); {', '.join(DISTRIBUTION_BASELINES)} is the trivial distribution every "
        "head must beat",
    )
    _add_bootstrap_and_runtime(e)
    e.set_defaults(func=_eval)


def _add_calibrate(psub: Any) -> None:
    """``predictor calibrate``."""
    c = psub.add_parser(
        "calibrate",
        help="conformal uncertainty regions: calibrate on validation windows, coverage on test",
        description="Split conformal calibration per horizon step on each split's validation windows (never its "
        "test scene), then the fraction of true test positions inside the 50/90/95 % regions, per step and pooled, "
        "with block-bootstrap intervals, and the model's own (uncalibrated) regions. Point forecasts (constant "
        "velocity, point weights) get an error model fitted on the split's training windows "
        "(crowdnav_mesrnn.calibration).",
    )
    c.add_argument(
        "--model", required=True, choices=MODELS, help=_models_help("which predictor (shipped unless --checkpoint)")
    )
    c.add_argument("--split", default="all", choices=(*SPLITS, "all"), help="split(s) to calibrate (default: all)")
    c.add_argument(
        "--score",
        default="scaled",
        choices=("scaled", "radius"),
        help="scaled: a per-step scale on the forecast's Gaussian (default); radius: a per-step disc in metres",
    )
    c.add_argument(
        "--method",
        default="split",
        choices=("split", "online"),
        help="split: split conformal thresholds from the validation windows (default); online: from them, a quantile "
        "tracker per step and level over the test scene in time order, fed each outcome once revealed "
        "(crowdnav_mesrnn.online_conformal)",
    )
    c.add_argument(
        "--reveal",
        default=None,
        choices=("window", "step", "observed"),
        help="online only: when an outcome updates the tracker. window (default): every step of a window once the "
        "whole window is observed (t + 12), when its scored pedestrians (present in all 20 frames) are known, "
        "strictly causal; step: step h at t + h, counting only pedestrians still present at t + 12 (optimistic); "
        "observed: step h at t + h over every pedestrian present through t + h, scored or not (strictly causal; "
        "with --gamma experts only)",
    )
    c.add_argument(
        "--gamma",
        default=None,
        choices=("validation", "experts"),
        help="online only: the tracker's step size. validation (default): one step size chosen on the validation "
        "scenes; experts: a tracker per step size of the grid, mixed online by their pinball loss (no validation "
        "choice)",
    )
    c.add_argument(
        "--head",
        default="point",
        choices=("point", "gaussian"),
        help=f"which shipped weights of {', '.join(LEARNED_MODELS)} (default point; "
        f"{', '.join(DISTRIBUTION_BASELINES)} always uses its own Gaussians)",
    )
    c.add_argument("--checkpoint", default=None, help="checkpoint path instead; may contain {split} and {model}")
    c.add_argument("--levels", type=float, nargs="+", default=[0.5, 0.9, 0.95], help="coverage levels")
    c.add_argument("--json", action="store_true", help="print the result as one JSON object")
    c.add_argument("--out", default=None, help="also write the JSON result here (atomically)")
    _add_bootstrap_and_runtime(c)
    c.set_defaults(func=_calibrate)


def _add_fit_head(psub: Any) -> None:
    """``predictor fit-head``."""
    f = psub.add_parser(
        "fit-head",
        help="fit the gaussian head on the shipped point weights, trunk frozen (MODEL_gaussian_SPLIT.pt)",
        description="The head-only shortcut of configs/predictor/gaussian.yaml (not the declared plan): loads the point "
        "weights, freezes every trunk and decoder parameter, fits the distribution head by NLL on the split's training "
        "windows (the node states of the mean rollout cached once), keeps the epoch of lowest validation NLL and writes "
        "MODEL_gaussian_SPLIT.pt beside the point weights (a head-only file naming the point weights and their SHA-256), "
        "where `evaluate --head gaussian` and `calibrate --head gaussian` look. Point weights are never modified "
        "(crowdnav_mesrnn.head_fit explains why the trunk is the declared recipe's).",
    )
    f.add_argument("--model", required=True, choices=LEARNED_MODELS, help="which structural RNN")
    f.add_argument("--split", default="all", choices=(*SPLITS, "all"), help="split(s) (default: all)")
    f.add_argument("--epochs", type=int, default=200, help="most L-BFGS iterations, each a pass over the rows (200)")
    f.add_argument("--patience", type=int, default=10, help="stop after this many without a lower val NLL (10)")
    f.add_argument(
        "--whiten-floor", type=float, default=1e-2, help="eigenvalue floor of the whitened fit, relative (default 1e-2)"
    )
    f.add_argument("--max-windows", type=int, default=0, help="use only the first N train and val windows (0: all)")
    f.add_argument(
        "--point", default=None, help="point weights instead of the shipped ones; may contain {split}, {model}"
    )
    f.add_argument("--out", default=None, help="output instead of the shipped path; may contain {split} and {model}")
    f.add_argument("--force", action="store_true", help="replace an existing output")
    f.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    f.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    f.set_defaults(func=_fit_head)


def _add_fit_cv_gaussian(psub: Any) -> None:
    """``predictor fit-cv-gaussian``."""
    f = psub.add_parser(
        "fit-cv-gaussian",
        help="fit cv_gaussian's scale a + b*h per split on its training windows (cv_gaussian_SPLIT.json)",
        description="Constant velocity with an isotropic Gaussian of scale a + b*h metres at horizon step h: fits a "
        "and b (a, b >= 0) by NLL on each split's training windows for the forms a + b*h, b*h and a, keeps the one "
        "with the lowest validation NLL (the two-parameter form only when it beats the better one-parameter form "
        "by more than 0.001 nats) and writes cv_gaussian_SPLIT.json; the held-out scene is never read "
        "(crowdnav_mesrnn.models.cv_gaussian_fit).",
    )
    f.add_argument("--split", default="all", choices=(*SPLITS, "all"), help="split(s) to fit (default: all)")
    f.add_argument(
        "--out-dir",
        default=None,
        help="folder of the parameter files (default: the shipped crowdnav_mesrnn/pretrained)",
    )
    f.add_argument("--force", action="store_true", help="replace existing parameter files")
    f.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    f.set_defaults(func=_fit_cv_gaussian)


def _add_export(psub: Any) -> None:
    """``predictor export``."""
    x = psub.add_parser("export", help="copy a trained checkpoint into the package's pretrained weights")
    x.add_argument("checkpoint", help="a training checkpoint (RUN/best.pt)")
    x.add_argument("--model", required=True, choices=LEARNED_MODELS, help="the model it holds (checked)")
    x.add_argument("--split", required=True, choices=SPLITS, help="the split it was trained for (checked)")
    x.add_argument("--note", default="", help="why this configuration was selected")
    x.set_defaults(func=_export)


def _add_select(psub: Any) -> None:
    """``predictor select``."""
    sel = psub.add_parser("select", help="export the run with the lowest validation ADE as the shipped weights")
    sel.add_argument("--model", required=True, choices=LEARNED_MODELS, help="the model the runs hold (checked)")
    sel.add_argument("--split", required=True, choices=SPLITS, help="the split they were trained for (checked)")
    sel.add_argument("runs", nargs="+", help="run folders holding best.pt")
    sel.set_defaults(func=_select)


def _add_report(psub: Any) -> None:
    """``predictor report``."""
    r = psub.add_parser("report", help="evaluate every predictor and write docs/results/predictors.md (+ .json)")
    r.add_argument(
        "--out", default=None, help="the page (default docs/results/predictors.md; required with --plan-only)"
    )
    r.add_argument("--extra", action="append", metavar="MODEL:LABEL=TEMPLATE", help="extra rows from checkpoints")
    r.add_argument("--plan", default=None, help="plan file whose seeds to report (configs/predictor/candidates.yaml)")
    _add_bootstrap_and_runtime(r)
    r.add_argument(
        "--render-only", action="store_true", help="rewrite the page from its .json (after a change of wording only)"
    )
    r.add_argument(
        "--claims",
        action="store_true",
        help="test the paper's further claims (density, motion type, collisions, difficulty) and add them to the "
        "existing page and its .json, keeping everything else",
    )
    r.add_argument(
        "--plan-only",
        action="store_true",
        help="a page for the --plan's runs alone (constant velocity and the plan's seeds; no shipped weights)",
    )
    r.set_defaults(func=_report)


def _add_plan(psub: Any) -> None:
    """``predictor plan``."""
    pl = psub.add_parser(
        "plan",
        help="train every run of a comparison plan (configs/predictor/candidates.yaml); resumable",
        description="Stages: candidates (every candidate x model x split), seeds (the candidate selected on "
        "validation data, every seed), all (both), export (ship the best-validation seed; explicit only). "
        "Finished runs are skipped, interrupted ones resumed.",
    )
    pl.add_argument("file", help="plan file, e.g. configs/predictor/candidates.yaml")
    pl.add_argument(
        "--stage", default="all", choices=("candidates", "seeds", "all", "export"), help="which stage (default: all)"
    )
    pl.add_argument("--dry-run", action="store_true", help="print every run, its status and the CPU-time estimate")
    pl.add_argument("--shard", default="0/1", metavar="I/N", help="run only runs I, I+N, ... (one process per core)")
    pl.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    pl.add_argument("--measure-batches", type=int, default=3, help="training batches timed per config (dry run)")
    pl.add_argument("--remeasure", action="store_true", help="ignore the cached throughputs (dry run)")
    pl.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    pl.set_defaults(func=main_plan)


def _add_plot(psub: Any) -> None:
    """``predictor plot``."""
    g = psub.add_parser("plot", help="draw observed paths, true futures and forecasts of one test window")
    g.add_argument("--split", required=True, choices=SPLITS, help="whose test windows (its held-out scene)")
    g.add_argument("--window", type=int, required=True, help="index among the split's test windows (>= 2 scored)")
    g.add_argument("--models", default="cv,vlstm,srnn,mesrnn", help="comma-separated models to draw (default: all)")
    g.add_argument("--out", default=None, help="PNG path (default docs/results/SPLIT_window_N.png)")
    g.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    g.set_defaults(func=_plot)


def add_parser(sub: Any) -> None:
    """Add ``predictor`` and its actions to the sub-parsers ``sub`` of the ``crowdnav-mesrnn`` parser."""
    p = sub.add_parser("predictor", help="train, evaluate, export and plot trajectory predictors")
    psub = p.add_subparsers(dest="predictor_cmd", required=True, metavar="ACTION")
    for add in (
        _add_train,
        _add_evaluate,
        _add_calibrate,
        _add_fit_head,
        _add_fit_cv_gaussian,
        _add_export,
        _add_select,
        _add_report,
        _add_plan,
        _add_plot,
    ):
        add(psub)
