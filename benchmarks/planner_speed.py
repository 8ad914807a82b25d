"""Episodes per second of each planner on the evaluation episodes of a held-out scene.

Run: ``python benchmarks/planner_speed.py [--split univ] [--predictor oracle] [--episodes 20] [--repeats 3]
[--n-envs 4]``. For each planner — straight-to-goal, the sampling planner (default and dense candidates), the
search planner and the PRIVILEGED ceiling — the first ``--episodes`` episodes of
:func:`agents.rollout.evaluation_seeds` run as ``agents.evaluate`` runs them (``--n-envs`` environments in
lockstep, one batched ``predict`` per step). Printed: the median over ``--repeats`` of episodes per second by
the process's CPU time (robust to a shared machine) and by wall time, the ratio of CPU time per episode against
the sampling planner measured the same way, the mean planning time per ``predict`` call, and the success rate of
the episodes (the same each repeat). Never asserts on time.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

from agents.evaluation.run import evaluation_env_kwargs
from agents.planners import make_planner
from agents.rollout import evaluation_seeds, run_episodes
from envs.crowd_nav import CrowdNavEnv

#: (label, planner name, options)
PLANNERS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("straight", "straight", {}),
    ("planner (sampling, 37)", "planner", {}),
    ("planner (sampling, dense 97)", "planner", {"candidates": "dense"}),
    ("search", "search", {}),
    ("privileged (PRIVILEGED)", "privileged", {}),
)


class _Timed:
    """A policy whose ``predict`` calls are timed (CPU seconds)."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.calls = 0
        self.seconds = 0.0
        self.privileged = getattr(policy, "privileged", False)
        if hasattr(policy, "bind_envs"):
            self.bind_envs = policy.bind_envs

    def predict(self, obs: Any, **kwargs: Any) -> Any:
        t0 = time.process_time()
        out = self.policy.predict(obs, **kwargs)
        self.seconds += time.process_time() - t0
        self.calls += 1
        return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="univ")
    p.add_argument("--predictor", default="oracle")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--n-envs", type=int, default=4)
    args = p.parse_args()
    kwargs = evaluation_env_kwargs("straight", args.predictor, args.split)
    envs = [CrowdNavEnv(**kwargs) for _ in range(args.n_envs)]
    seeds = evaluation_seeds(args.split, args.episodes)
    print(
        f"{args.episodes} evaluation episodes of {args.split} (forecasts {args.predictor}), {args.n_envs} envs in "
        f"lockstep, median of {args.repeats} repeats"
    )
    measured = []
    for label, name, options in PLANNERS:
        cpu, wall, per_call, success = [], [], [], 0.0
        for _ in range(args.repeats):
            policy = _Timed(make_planner(name, envs[0].config, **options))
            c0, w0 = time.process_time(), time.perf_counter()
            rows = run_episodes(policy, envs, seeds)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
            per_call.append(1000 * policy.seconds / max(policy.calls, 1))
            success = sum(r["outcome"] == "success" for r in rows) / len(rows)
        measured.append((label, statistics.median(cpu), statistics.median(wall), statistics.median(per_call), success))
    reference = next(cpu for label, cpu, *_ in measured if label.startswith("planner (sampling, 37)"))
    print(f"{'planner':<30}{'episodes/s (CPU)':>18}{'episodes/s (wall)':>19}{'CPU vs sampling':>17}"
          f"{'ms/predict':>12}{'success':>9}")  # fmt: skip
    for label, cpu, wall, ms, success in measured:
        print(
            f"{label:<30}{args.episodes / cpu:>18.2f}{args.episodes / wall:>19.2f}{cpu / reference:>16.1f}x"
            f"{ms:>12.1f}{success:>9.2f}"
        )


if __name__ == "__main__":
    main()
