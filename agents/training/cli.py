"""The command line of training: ``python -m agents.train`` and ``crowdnav-mesrnn agent train``."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Final

from agents.entry import module_main, parse_set
from agents.training.config import DEFAULT_CONFIG, TrainConfig, load_train_config
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP

#: The description of ``python -m agents.train --help``.
DESCRIPTION: Final[str] = (
    "Train a navigation policy (PPO or SAC) on ``CrowdNav-*`` from a YAML config; every run is a folder."
)


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        default=None,
        help="training YAML (default: configs/agent/ppo.yaml; with --resume: the run's config.yaml)",
    )
    p.add_argument(
        "--predictor",
        default=None,
        metavar="PREDICTOR",
        help=f"forecast arm: {', '.join(predictors.names(plugins=False))}, an installed predictor plug-in or an "
        "import path package.module:Factory (default: mesrnn)",
    )
    p.add_argument("--split", default=None, choices=SPLITS, help="train on its four training scenes (default: zara1)")
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--seed", type=int, default=None, help="seed (default: 0)")
    p.add_argument("--timesteps", type=float, default=None, help="total environment steps (overrides n_timesteps)")
    p.add_argument("--out", default=None, help="run folder (default: runs/<algo>_<predictor>_<split>_s<seed>_<time>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        metavar="KEY=VALUE",
        help="override a config key, value as YAML: learning_rate=1e-4, env.time_penalty=-0.01, "
        "policy_kwargs.net_arch=[64,64], eval.episodes=50, pretrain.episodes=300, pretrain=null",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The :class:`TrainConfig` of parsed command-line arguments."""
    if args.resume and not args.out:
        raise ConfigError("--resume needs --out RUN_DIR")
    path = args.config
    if path is None:
        saved = Path(args.out) / "config.yaml" if args.out else None
        path = saved if args.resume and saved is not None and saved.is_file() else DEFAULT_CONFIG
    overrides = parse_set(args.overrides)
    for key in ("predictor", "split", "seed"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    if args.timesteps is not None:
        overrides["n_timesteps"] = args.timesteps
    return load_train_config(path, None, overrides)


def run_from_args(args: argparse.Namespace, command: str | None = None) -> int:
    cfg = config_from_args(args)  # every argument and config key checked before SB3 and torch are imported
    from agents.training.run import train

    run_dir = train(cfg, args.out, resume=args.resume, progress=not args.no_progress, command=command)
    done = json.loads((run_dir / "DONE").read_text())
    best = done.get("best_validation") or {}
    msg = f"run folder {run_dir}: {done['steps']} steps"
    if best:
        msg += f"; best validation success {best['success_rate']:.3f} at step {best['step']}"
    print(msg)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.train ...`` (its command line is recorded in the run's ``command.txt``)."""

    def run(args: argparse.Namespace) -> int:
        return run_from_args(
            args, shlex.join(["python", "-m", "agents.train", *(sys.argv[1:] if argv is None else argv)])
        )

    return module_main("python -m agents.train", DESCRIPTION, add_train_arguments, run, argv)
