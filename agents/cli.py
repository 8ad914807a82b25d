"""The agents' subcommands of ``crowdnav-mesrnn``: ``demo``, ``agent`` and ``ablation``.

Each ``add_*`` function is named in :data:`crowdnav_mesrnn.cli.COMMANDS` and imported only when its
subcommand runs.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Final

from agents.demo_episode import CANDIDATE_SEEDS, DEMO_SEED
from crowdnav_mesrnn import predictors
from crowdnav_mesrnn.data.constants import SPLITS
from crowdnav_mesrnn.data.paths import DATA_DIR_HELP


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3f}"
    return "-" if value is None else str(value)


#: The help of ``--trust-pickle`` (``demo``, ``agent evaluate``, ``agent export``).
TRUST_PICKLE_HELP: Final[str] = (
    "allow loading an SB3 .zip and its _vecnormalize.pkl, which are unpickled and can run arbitrary code: only for "
    "files you trust (policy files of the project's format, NAME.policy.yaml, never need it)"
)


#: The shipped policy: PPO with MESRNN forecasts trained on the zara1 split's training scenes by ``agent train``,
#: a policy file of the project's format (data only, :mod:`agents.policy_file`; weights in ``ppo_mesrnn_zara1.pt``).
SHIPPED_POLICY: Final[Path] = Path(__file__).resolve().parent / "pretrained" / "ppo_mesrnn_zara1.policy.yaml"
#: The split whose training scenes the shipped policy was trained on (its held-out scene is the only one it may cross).
SHIPPED_SPLIT: Final[str] = "zara1"


def _demo_policy(args: argparse.Namespace) -> tuple[str, str | None]:
    """The policy spec of the demo and a note saying why it is not the shipped policy (or None)."""
    if args.policy is not None:
        return args.policy, None
    if args.split != SHIPPED_SPLIT:
        return "planner", (
            f"the shipped PPO policy was trained on the {SHIPPED_SPLIT} split's training scenes, which include the "
            f"{args.split} held-out scene: the sampling planner crosses it instead"
        )
    if not SHIPPED_POLICY.is_file():
        return "planner", f"no shipped PPO policy in this installation ({SHIPPED_POLICY}): the sampling planner drives"
    return str(SHIPPED_POLICY), None


def _demo_setup(args: argparse.Namespace, render: bool) -> tuple[Any, Any, str, str]:
    """The demo's environment and policy from its arguments: ``(env, policy, spec, label)``, ``label`` naming the
    policy and the forecasts it was trained with. Notes and warnings (a substitute policy, crowd or predictor) go to
    stderr."""
    from agents.planners import PLANNERS
    from agents.runs import check_trust, model_path

    spec, note = _demo_policy(args)
    if spec not in PLANNERS:  # a missing policy is named before torch and pymunk are imported
        model_path(spec)
    check_trust(spec, trust_pickle=args.trust_pickle)  # an SB3 zip is refused before anything reads it

    from agents.evaluation.run import evaluation_env_kwargs
    from agents.runs import check_spaces, load_policy, run_settings
    from crowdnav_mesrnn.data.paths import HOW_TO_GET_DATA, data_available
    from envs.crowd_nav import CrowdNavEnv
    from envs.forecasting.factory import PredictorUnavailableError

    if note:
        print(f"note: {note}", file=sys.stderr)
    crowd = "synthetic" if args.synthetic else "replay"
    if crowd == "replay" and not data_available(args.data_dir):
        print(f"warning: no ETH/UCY data found; the demo uses the synthetic crowd. {HOW_TO_GET_DATA}", file=sys.stderr)
        crowd = "synthetic"
    trained_on = run_settings(spec).get("run", {}).get("predictor") if spec not in PLANNERS else None
    predictor = args.predictor or trained_on or "mesrnn"
    overrides = {"crowd": crowd, "data_dir": args.data_dir}
    render_mode = "rgb_array" if render else None
    kwargs = evaluation_env_kwargs(spec, predictor, args.split, overrides, require_pedestrians=True)
    try:
        env = CrowdNavEnv(render_mode=render_mode, **kwargs)
    except PredictorUnavailableError as exc:
        if args.predictor is not None:
            raise
        print(f"warning: {exc}\nwarning: falling back to constant-velocity ('cv') forecasts.", file=sys.stderr)
        kwargs["predictor"] = "cv"
        env = CrowdNavEnv(render_mode=render_mode, **kwargs)
    policy = load_policy(spec, env.config, trust_pickle=args.trust_pickle)
    if hasattr(policy, "bind_envs"):  # the privileged ceiling reads the environment itself
        policy.bind_envs([env])
    check_spaces(policy, env)
    label = spec if spec in PLANNERS else f"{spec} (trained with {trained_on or 'unknown'} forecasts)"
    return env, policy, spec, label


def _choose_seed(args: argparse.Namespace) -> int:
    """``demo --choose-seed``: apply the rule of :mod:`agents.demo_episode` and print its candidates and result."""
    from agents import demo_episode
    from agents.rollout import run_episodes

    started = time.perf_counter()
    env, policy, _, label = _demo_setup(args, render=False)
    seeds = list(range(demo_episode.CANDIDATE_SEEDS))
    print(
        f"demo --choose-seed: policy {label}, split {args.split}, forecasts {env.predictor_name}; "
        f"reset seeds 0..{seeds[-1]} (rule: agents/demo_episode.py)"
    )
    rows = run_episodes(policy, [env], seeds, progress=sys.stderr.isatty(), desc="candidate episodes")
    env.close()
    candidates = demo_episode.judge(rows)
    chosen = demo_episode.choose(candidates)
    print(demo_episode.table(candidates, chosen))
    kept = sum(c.verdict == "kept" for c in candidates)
    if chosen is None:
        print(f"chosen seed: none (no successful episode with path ratio >= {demo_episode.MIN_PATH_RATIO:g})")
    else:
        print(f"chosen seed: {chosen} (the most crowded of {kept} kept; default --seed is {demo_episode.DEMO_SEED})")
    print(f"done in {time.perf_counter() - started:.1f} s")
    return 0 if chosen is not None else 1


def _demo(args: argparse.Namespace) -> int:
    if args.choose_seed:
        return _choose_seed(args)
    from envs.rendering import save_gif

    started = time.perf_counter()
    env, policy, spec, name = _demo_setup(args, render=not args.no_gif)

    obs, info = env.reset(seed=args.seed)
    scene = f"{info['recording']} ({info['crowd']})"
    print(
        f"demo: policy {name}, split {args.split}, scene {scene}, forecasts {env.predictor_name}, seed {args.seed}, "
        f"start {[round(v, 2) for v in info['start']]} -> goal {[round(v, 2) for v in info['goal']]}, "
        f"t0 {info['t0_s']:.1f} s, time limit {info['time_limit_s']:.1f} s"
    )
    frames = [] if args.no_gif else [env.render()]
    done = False
    step_info: dict[str, Any] = {}
    while not done:
        action, _ = policy.predict(obs, deterministic=True)
        obs, _, terminated, truncated, step_info = env.step(action)
        if not args.no_gif:
            frames.append(env.render())
        done = terminated or truncated
    metrics = step_info["episode_metrics"]
    env.close()
    if args.json:
        record = {"scene": info["recording"], "predictor": env.predictor_name, "policy": str(spec), **metrics}
        print(json.dumps(record, indent=2))
    else:  # the keys of the JSON (and of info["episode_metrics"]), each with its readable label
        from envs.rewards import METRIC_LABELS

        width = max(len(key) for key in metrics)
        for key, value in metrics.items():
            print(f"  {key:<{width}}  {_fmt(value):<10}  {METRIC_LABELS.get(key, '')}".rstrip())
    if not args.no_gif:
        path = save_gif(frames, args.out, fps=env.metadata["render_fps"])
        print(f"wrote {path} ({len(frames)} frames)")
    print(f"done in {time.perf_counter() - started:.1f} s")
    return 0


def add_demo(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="a policy crosses a held-out ETH/UCY scene with forecasts; prints metrics, writes a GIF",
        description=(
            "A policy crosses the held-out scene of a split with MESRNN forecasts and the episode is written as a GIF "
            "with the forecasts drawn. The default policy is the shipped PPO policy (trained by this project's "
            "'agent train' on the zara1 split's training scenes) when it is installed and the split is zara1, else the "
            "sampling planner. Without ETH/UCY data the synthetic crowd is crossed instead (and the demo says so); "
            "without the MESRNN weights, constant-velocity forecasts (with a warning)."
        ),
    )
    p.add_argument(
        "--policy",
        default=None,
        help="planner, search, straight, privileged (PRIVILEGED: reads the replay's true future), or a trained model "
        "(NAME.policy.yaml, a run folder, or an SB3 .zip with --trust-pickle); default: the shipped PPO policy",
    )
    p.add_argument("--trust-pickle", action="store_true", help=TRUST_PICKLE_HELP)
    p.add_argument("--split", default="zara1", choices=SPLITS, help="its held-out scene is crossed (default: zara1)")
    p.add_argument(
        "--predictor",
        default=None,
        choices=predictors.names(plugins=False),
        help="forecast source (default: the policy's own, else mesrnn; cv when the MESRNN weights are missing)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=DEMO_SEED,
        help=f"episode seed (default: {DEMO_SEED}, the episode --choose-seed picks for the shipped policy on zara1)",
    )
    p.add_argument(
        "--choose-seed",
        action="store_true",
        help=f"apply the rule that picks the default episode (agents/demo_episode.py) to reset seeds "
        f"0..{CANDIDATE_SEEDS - 1} of this policy, split and forecasts: print each candidate and the chosen seed",
    )
    p.add_argument("--out", default="demo.gif", help="GIF path (default: demo.gif)")
    p.add_argument("--no-gif", action="store_true", help="do not render or write a GIF")
    p.add_argument("--synthetic", action="store_true", help="use the synthetic crowd even when ETH/UCY data is found")
    p.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    p.add_argument("--json", action="store_true", help="print the metrics as one JSON object")
    p.set_defaults(func=_demo)


def _export(args: argparse.Namespace) -> int:
    from agents.policy_file import weights_file_name
    from agents.runs import export_policy

    dest = export_policy(args.run, args.dest, args.model, trust_pickle=args.trust_pickle)
    weights = dest.with_name(weights_file_name(dest))
    print(f"wrote {dest} and {weights.name} ({weights.stat().st_size / 1e6:.2f} MB)")
    return 0


def add_agent(sub: Any) -> None:
    from agents.evaluation.cli import add_evaluate_arguments
    from agents.evaluation.cli import run_from_args as evaluate_from_args
    from agents.runs import RUN_MODELS
    from agents.training.cli import add_train_arguments
    from agents.training.cli import run_from_args as train_from_args

    p = sub.add_parser("agent", help="train and evaluate navigation policies (PPO, SAC, planners)")
    asub = p.add_subparsers(dest="agent_cmd", required=True, metavar="ACTION")
    t = asub.add_parser(
        "train",
        help="train PPO/SAC from a YAML config into a run folder (same as python -m agents.train)",
        description="Train a policy from a YAML config (RL Zoo layout) into a run folder; see agents/train.py.",
    )
    add_train_arguments(t)
    t.set_defaults(func=lambda args: train_from_args(args, shlex.join(["crowdnav-mesrnn", *sys.argv[1:]])))
    e = asub.add_parser(
        "evaluate",
        help="evaluate a run, a model or a planner on a held-out scene (same as python -m agents.evaluate)",
        description="Evaluate a policy on the held-out scene of a split over the fixed, seeded list of episodes.",
    )
    add_evaluate_arguments(e)
    e.set_defaults(func=evaluate_from_args)
    x = asub.add_parser(
        "export",
        help="write a run's model as a policy file of the project's format (data only), to evaluate or ship it alone",
        description=(
            "Write RUN's best (or final) model as DEST (NAME.policy.yaml: architecture, spaces, normalisation "
            "statistics and training config as plain YAML) and NAME.pt beside it (the weights, read with "
            "torch.load(weights_only=True)); loading them unpickles nothing. A run folder of 'agent train' holds this "
            "format already and it is copied; an SB3 .zip (an older run, a model file with its <stem>.yaml) is "
            "converted, which unpickles it: only with --trust-pickle."
        ),
    )
    x.add_argument("run", help="a run folder of agents.train, a policy file, or an SB3 .zip (with --trust-pickle)")
    x.add_argument("dest", help="destination NAME.policy.yaml (e.g. agents/pretrained/ppo_mesrnn_zara1.policy.yaml)")
    x.add_argument("--model", default="best", choices=RUN_MODELS, help="best or final model (default: best)")
    x.add_argument("--trust-pickle", action="store_true", help=TRUST_PICKLE_HELP)
    x.set_defaults(func=_export)
    from agents.curves import add_curves_arguments
    from agents.curves import run_from_args as curves_from_args

    c = asub.add_parser(
        "curves",
        help="plot validation success against environment steps of run folders (same as python -m agents.curves)",
        description="Learning curves: validation success (95 %% Wilson band) against PPO environment steps.",
    )
    add_curves_arguments(c)
    c.set_defaults(func=curves_from_args)


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
