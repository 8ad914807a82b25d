"""The command line of the policy bench: ``crowdnav-mesrnn bench-policy IMPORT_PATH`` and
``python -m agents.policy_bench``.

Every argument is checked here, before the environment, torch or SB3 is imported: a malformed import path, a
package that is not installed, an unknown arm, split or environment setting is refused in about a second.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_ENV_HELP

#: Defaults (repeated from agents.policy_bench.run, which imports more than a command line should).
_ARMS = "none,cv,mesrnn,oracle"
_EPISODES = 100


def _names(values: Sequence[str] | str) -> list[str]:
    """``a,b c`` -> ``[a, b, c]`` (commas or spaces, repeats dropped, order kept)."""
    items = [values] if isinstance(values, str) else list(values)
    return list(dict.fromkeys(x for v in items for x in re.split(r"[,\s]+", v) if x))


def default_out(policy: str) -> Path:
    """``runs/bench-policy/<import path, file-name safe>``."""
    return Path("runs") / "bench-policy" / re.sub(r"[^\w.-]", "_", policy)


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "bench-policy",
        help="benchmark your own policy against the shipped planners and the privileged ceiling, one page",
        description=(
            "Runs the policy at IMPORT_PATH (package.module:attr: an object with SB3's predict(obs, "
            "deterministic=True), a callable obs -> action, or a factory of one) on the fixed episode lists of the "
            "held-out scenes with each forecast arm, against the sampling and search planners and the privileged "
            "ceiling on the same episodes (from the committed planner grid when it holds them, else run here), "
            "with exact McNemar tests (Holm), and writes report.md, report.json and success_by_scene.png into --out. "
            "The contract: docs/policies.md."
        ),
    )
    p.add_argument("policy", metavar="IMPORT_PATH", help="package.module:attr")
    p.add_argument(
        "--arms",
        nargs="+",
        default=[_ARMS],
        metavar="ARM",
        help=f"forecast arms, comma- or space-separated (default: {_ARMS}); any forecast source or plug-in",
    )
    p.add_argument(
        "--splits",
        nargs="+",
        default=list(SPLITS),
        metavar="SPLIT",
        help=f"whose held-out scenes, comma- or space-separated (default: all five: {','.join(SPLITS)})",
    )
    p.add_argument(
        "--episodes",
        type=int,
        default=_EPISODES,
        help=f"episodes per scene and arm: the first N of each scene's fixed list (default: {_EPISODES}; the "
        "planner grid has 500)",
    )
    p.add_argument("--seed", type=int, default=0, help="which fixed episode list (default: 0, the grids')")
    p.add_argument("--out", default=None, help="output folder (default: runs/bench-policy/IMPORT_PATH)")
    p.add_argument(
        "--rerun-references",
        action="store_true",
        help="run the planners and the ceiling here even where the committed grid holds the same episodes",
    )
    p.add_argument("--set", dest="env_set", action="append", metavar="KEY=VALUE", help="environment setting, for all")
    p.add_argument("--n-envs", type=int, default=4, help="environments stepped in lockstep (default: 4)")
    p.add_argument("--data-dir", dest="data_dir_env", metavar="DIR", default=None, help=DATA_DIR_ENV_HELP)
    p.add_argument("--force", action="store_true", help="replace a report in --out of another policy or settings")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def check_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """The checked settings of a bench (raises ``ValueError``/``ConfigError`` naming what is wrong), importing
    neither the environment nor torch."""
    from agents.entry import parse_set
    from agents.policy_bench.policy import check_import_path
    from crowdnav_mesrnn import predictors
    from envs.config import config_from

    check_import_path(args.policy)
    arms = _names(args.arms)
    splits = _names(args.splits)
    if not arms or not splits:
        raise ValueError("--arms and --splits need at least one name each")
    for arm in arms:
        predictors.check(arm)
    bad = [s for s in splits if s not in SPLITS]
    if bad:
        raise ValueError(f"unknown split(s) {', '.join(bad)}; valid: {', '.join(SPLITS)}")
    if args.episodes < 1 or args.n_envs < 1:
        raise ValueError(f"--episodes and --n-envs must be >= 1, got {args.episodes} and {args.n_envs}")
    env = parse_set(args.env_set)
    config_from({**env, "predictor": arms[0], "split": splits[0], "part": "test"}, {})  # unknown keys, bad values
    out = Path(args.out) if args.out else default_out(args.policy)
    settings = {"policy": args.policy, "splits": splits, "arms": arms, "episodes": args.episodes, "seed": args.seed}
    if not args.force:
        _check_replace(out / "report.json", {**settings, "env": env})
    return {**settings, "env": env, "out": out}


def _check_replace(path: Path, settings: dict[str, Any]) -> None:
    """Refuse to replace a report of another policy, list or settings (``--force`` does)."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    held = {**(old.get("config") or {}), "policy": old.get("policy")}
    differ = [k for k, v in settings.items() if held.get(k) != v]
    if differ:
        raise ValueError(
            f"{path} holds a bench of other {', '.join(differ)} ({', '.join(f'{k}={held.get(k)!r}' for k in differ)}); "
            "choose another --out, or pass --force to replace it"
        )


def _run(args: argparse.Namespace) -> int:
    checked = check_arguments(args)
    from agents.policy_bench.run import PolicyBenchConfig, run_policy_bench

    cfg = PolicyBenchConfig(
        policy=checked["policy"],
        splits=tuple(checked["splits"]),
        arms=tuple(checked["arms"]),
        episodes=checked["episodes"],
        seed=checked["seed"],
        env=checked["env"],
        rerun_references=args.rerun_references,
        n_envs=args.n_envs,
    )
    out = checked["out"]
    command = "crowdnav-mesrnn " + shlex.join(sys.argv[1:]) if sys.argv[1:2] == ["bench-policy"] else ""
    run_policy_bench(cfg, out, command=command, progress=not args.no_progress, log=lambda m: print(m, flush=True))
    print(f"report: {out / 'report.md'} (+ report.json, success_by_scene.png)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agents.policy_bench``: the same as ``crowdnav-mesrnn bench-policy``."""
    from crowdnav_mesrnn.cli import main as cli_main

    return cli_main(["bench-policy", *(sys.argv[1:] if argv is None else argv)])
