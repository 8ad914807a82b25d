"""The agents' subcommands of ``crowdnav-mesrnn``: ``demo``, ``agent`` and ``ablation``.

Each ``add_*`` function is named in :data:`crowdnav_mesrnn.cli.COMMANDS` and imported only when its
subcommand runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from crowdnav_mesrnn.data.constants import SPLITS

_PREDICTORS = ("none", "cv", "mesrnn", "srnn", "vlstm", "oracle", "noisy_oracle")


def module_main(
    prog: str,
    doc: str | None,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], int],
    argv: Sequence[str] | None = None,
) -> int:
    """``main()`` of a ``python -m agents.<module>`` command: parse, run, and turn configuration and input errors
    into a message and exit status 2 (as ``crowdnav-mesrnn`` does)."""
    from crowdnav_mesrnn.config import ConfigError

    parser = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0] or None)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except (ConfigError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3f}"
    return "-" if value is None else str(value)


def _demo(args: argparse.Namespace) -> int:
    from agents.planners import SamplingPlanner
    from crowdnav_mesrnn.data.paths import HOW_TO_GET_DATA, data_available
    from envs.crowd_nav import CrowdNavEnv
    from envs.forecasts import PredictorUnavailableError
    from envs.rendering import save_gif

    started = time.perf_counter()
    crowd = "synthetic" if args.synthetic else "replay"
    if crowd == "replay" and not data_available(args.data_dir):
        print(f"warning: no ETH/UCY data found; the demo uses the synthetic crowd. {HOW_TO_GET_DATA}", file=sys.stderr)
        crowd = "synthetic"
    predictor = args.predictor or "mesrnn"
    kwargs: dict[str, Any] = {
        "split": args.split,
        "part": "test",
        "crowd": crowd,
        "data_dir": args.data_dir,
        "render_mode": None if args.no_gif else "rgb_array",
    }
    try:
        env = CrowdNavEnv(predictor=predictor, **kwargs)
    except PredictorUnavailableError as exc:
        if args.predictor is not None:
            raise
        print(f"warning: {exc}\nwarning: falling back to constant-velocity ('cv') forecasts.", file=sys.stderr)
        predictor = "cv"
        env = CrowdNavEnv(predictor=predictor, **kwargs)

    policy = SamplingPlanner(env.config)
    obs, info = env.reset(seed=args.seed)
    scene = f"{info['recording']} ({info['crowd']})"
    print(
        f"demo: split {args.split}, scene {scene}, forecasts {env.predictor_name}, seed {args.seed}, "
        f"start {[round(v, 2) for v in info['start']]} -> goal {[round(v, 2) for v in info['goal']]}, "
        f"t0 {info['t0_s']:.1f} s, time limit {info['time_limit_s']:.1f} s"
    )
    frames = [] if args.no_gif else [env.render()]
    done = False
    step_info: dict[str, Any] = {}
    while not done:
        obs, _, terminated, truncated, step_info = env.step(policy(obs))
        if not args.no_gif:
            frames.append(env.render())
        done = terminated or truncated
    metrics = step_info["episode"]
    env.close()
    if args.json:
        print(json.dumps({"scene": info["recording"], "predictor": env.predictor_name, **metrics}, indent=2))
    else:
        width = max(len(k) for k in metrics)
        for key, value in metrics.items():
            print(f"  {key:<{width}}  {_fmt(value)}")
    if not args.no_gif:
        path = save_gif(frames, args.out, fps=env.metadata["render_fps"])
        print(f"wrote {path} ({len(frames)} frames)")
    print(f"done in {time.perf_counter() - started:.1f} s")
    return 0


def add_demo(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="a scripted robot crosses a held-out ETH/UCY scene with forecasts; prints metrics, writes a GIF",
        description=(
            "A scripted robot (straight to the goal, slowing or swerving for forecast conflicts) crosses the "
            "held-out scene of a split with MESRNN forecasts (constant velocity, with a warning, when the "
            "pretrained weights are missing), or the synthetic crowd when no ETH/UCY data is found."
        ),
    )
    p.add_argument("--split", default="zara1", choices=SPLITS, help="its held-out scene is crossed (default: zara1)")
    p.add_argument(
        "--predictor",
        default=None,
        choices=_PREDICTORS,
        help="forecast source (default: mesrnn, falling back to cv when its weights are missing)",
    )
    p.add_argument("--seed", type=int, default=0, help="episode seed (default: 0)")
    p.add_argument("--out", default="demo.gif", help="GIF path (default: demo.gif)")
    p.add_argument("--no-gif", action="store_true", help="do not render or write a GIF")
    p.add_argument("--synthetic", action="store_true", help="use the synthetic crowd even when ETH/UCY data is found")
    p.add_argument("--data-dir", default=None, help="data folder (default: $CROWDNAV_MESRNN_DATA, ...)")
    p.add_argument("--json", action="store_true", help="print the metrics as one JSON object")
    p.set_defaults(func=_demo)


def add_agent(sub: Any) -> None:
    p = sub.add_parser("agent", help="train and evaluate navigation policies (PPO, SAC, planners)")
    p.set_defaults(func=lambda args: _not_yet("agent"))


def add_ablation(sub: Any) -> None:
    from agents.ablation import add_arguments, run_from_args

    p = sub.add_parser(
        "ablation",
        help="run the planning-aid ablation grid (resumable cells, local pool or Ray) and summarise it",
        description=(
            "Forecast arms x policies x seeds x held-out splits from a grid YAML, as resumable cells "
            "(runs/ablation/<name>/), summarised with intervals and paired tests into results/ablation/<name>/. "
            "Same as python -m agents.ablation."
        ),
    )
    add_arguments(p)
    p.set_defaults(func=run_from_args)


def _not_yet(name: str) -> int:
    print(f"crowdnav-mesrnn {name}: not implemented yet", file=sys.stderr)
    return 2
