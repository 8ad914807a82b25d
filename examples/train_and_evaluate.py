"""Train a navigation policy and evaluate it on the held-out scene, in a few lines.

    python examples/train_and_evaluate.py                       # the recipe's budget (docs/first-hour.md: timings)
    python examples/train_and_evaluate.py --tiny --out /tmp/x   # a smoke run of under a minute (CI runs this)

The recipe is ``configs/agent/ppo.yaml`` (a DAgger warm start from the sampling planner, then PPO); the policy
sees MESRNN forecasts (``--predictor``, any forecast arm or installed predictor plug-in) and is trained on the
four training scenes of ``--split``, then evaluated on its held-out scene against the sampling planner with the
same forecasts, on the same seeded episodes.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.evaluation import evaluate, format_summary
from agents.training import load_train_config, train

#: Overrides that shrink a run to seconds: tiny networks, a two-episode warm start and validation.
TINY = {
    "n_envs": 1,
    "n_timesteps": 128,
    "n_steps": 64,
    "batch_size": 32,
    "n_epochs": 1,
    "policy_kwargs.net_arch": [16],
    "policy_kwargs.features_extractor_kwargs.hidden_dim": 8,
    "pretrain.episodes": 2,
    "pretrain.dagger_rounds": 0,
    "pretrain.epochs": 1,
    "pretrain.n_envs": 2,
    "eval.episodes": 2,
    "eval.n_envs": 2,
    "eval.freq_steps": 64,
    "checkpoint_freq_steps": 64,
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--predictor", default="mesrnn", help="forecast arm the policy sees (default: mesrnn)")
    p.add_argument("--split", default="zara1", help="held-out scene; trained on the other four (default: zara1)")
    p.add_argument("--episodes", type=int, default=None, help="evaluation episodes (default: 500, or 5 with --tiny)")
    p.add_argument("--tiny", action="store_true", help="a smoke run (under a minute) instead of the recipe")
    p.add_argument("--out", default="runs/example", help="run folder (default: runs/example)")
    args = p.parse_args()
    episodes = args.episodes or (5 if args.tiny else 500)

    # 1. train: the recipe, for this forecast arm and split
    overrides = {"predictor": args.predictor, "split": args.split, **(TINY if args.tiny else {})}
    cfg = load_train_config("configs/agent/ppo.yaml", overrides=overrides)
    run = train(cfg, Path(args.out) / "policy", progress=not args.tiny)

    # 2. evaluate the trained policy and the sampling planner on the same held-out episodes
    for policy in (run, "planner"):
        summary = evaluate(policy, args.predictor, args.split, episodes, out_dir=Path(args.out) / Path(policy).name)
        print(f"--- {policy}")
        print(format_summary(summary))


if __name__ == "__main__":
    main()
