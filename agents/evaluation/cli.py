"""The command line of an evaluation: ``python -m agents.evaluate`` and ``crowdnav-mesrnn agent evaluate``."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Final

from agents.entry import module_main, parse_set
from agents.evaluation import EPISODE_SOURCES
from agents.planners import PLANNERS
from agents.runs import RUN_MODELS, check_trust, model_path
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP

#: The description of ``python -m agents.evaluate --help``.
DESCRIPTION: Final[str] = (
    "Evaluate a policy — a training run, an SB3 model, or a planner — on a fixed, seeded list of episodes."
)


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "policy",
        help="a run folder of agents.train, a policy file NAME.policy.yaml, an SB3 .zip (with --trust-pickle), or a "
        "planner: 'straight', 'planner' (sampling), 'search', 'privileged' (PRIVILEGED ceiling: reads the replay's "
        "true future)",
    )
    p.add_argument(
        "--trust-pickle",
        action="store_true",
        help="allow loading an SB3 .zip and its _vecnormalize.pkl, which are unpickled and can run arbitrary code: "
        "only for files you trust (policy files, NAME.policy.yaml, never need it)",
    )
    p.add_argument(
        "--predictor",
        default="mesrnn",
        metavar="PREDICTOR",
        help=f"forecast arm: {', '.join(predictors.names(plugins=False))}, an installed predictor plug-in or an "
        "import path package.module:Factory (default: mesrnn)",
    )
    p.add_argument("--split", default="zara1", choices=SPLITS, help="its held-out scene is replayed (default: zara1)")
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--episodes", type=int, default=500, help="number of episodes (default: 500)")
    p.add_argument("--seed", type=int, default=0, help="which seeded list of episodes (default: 0)")
    p.add_argument(
        "--episodes-from",
        default="test",
        choices=EPISODE_SOURCES,
        help="test: the split's held-out scene (results); val: its training scenes' validation period, the episodes "
        "choices are made on (default: test)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="folder for episodes.csv and summary.json (default: a new runs/eval/<policy>_<predictor>_<split>_s<seed>_<time>)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument(
        "--all-episodes",
        action="store_true",
        help="keep episodes in which no pedestrian comes near the path (default: require one)",
    )
    p.add_argument("--model", default="best", choices=RUN_MODELS, help="model of a run folder (default: best)")
    p.add_argument(
        "--planner-set",
        dest="planner_set",
        action="append",
        metavar="KEY=VALUE",
        help="planner option, e.g. candidates=dense (sampling planner), lookahead_steps=8 (search), "
        "max_states=3000 (privileged)",
    )
    p.add_argument(
        "--ceiling",
        default=None,
        metavar="PATH",
        help="the privileged ceiling's episodes.csv (or --out folder) on the same episodes: report success / ceiling",
    )
    p.add_argument("--n-envs", type=int, default=4, help="environments stepped in lockstep (default: 4)")
    p.add_argument("--set", dest="env_set", action="append", metavar="KEY=VALUE", help="environment setting override")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_from_args(args: argparse.Namespace) -> int:
    predictors.check(args.predictor)  # a mistyped arm or a missing policy is named before torch is imported
    if args.policy not in PLANNERS:
        model_path(args.policy, args.model)
    check_trust(args.policy, args.model, args.trust_pickle)  # an SB3 zip is refused before anything reads it
    import torch

    from agents.evaluation.run import default_eval_dir, evaluate
    from agents.evaluation.summary import format_summary

    torch.set_num_threads(1)
    out = Path(args.out) if args.out else default_eval_dir(args.policy, args.predictor, args.split, args.seed)
    summary = evaluate(
        args.policy,
        args.predictor,
        args.split,
        args.episodes,
        seed=args.seed,
        out_dir=out,
        env_overrides=parse_set(args.env_set),
        require_pedestrians=not args.all_episodes,
        n_envs=args.n_envs,
        which=args.model,
        planner_kwargs=parse_set(args.planner_set),
        ceiling=args.ceiling,
        progress=not (args.no_progress or args.json),
        trust_pickle=args.trust_pickle,
        episodes_from=args.episodes_from,
    )
    if args.json:
        print(json.dumps(summary))
    else:
        print(format_summary(summary))
        print(f"wrote {out / 'episodes.csv'} and {out / 'summary.json'}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.evaluate ...``."""
    return module_main("python -m agents.evaluate", DESCRIPTION, add_evaluate_arguments, run_from_args, argv)
