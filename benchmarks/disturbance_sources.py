"""How much of the disturbance metrics is the robot's doing, and how much the reaction model's own motion.

Run: ``python benchmarks/disturbance_sources.py [--split univ] [--episodes 60] [--policies planner still]
[--variants ...] [--set KEY=VALUE ...]``. Each variant runs the evaluation's episodes
(:func:`agents.rollout.evaluation_seeds`, seed 0: the first ``--episodes`` of the grid's list) with the sampling
planner (``make_planner("planner")``, arm ``none``, as the grid's ``planner@<reaction>`` cells) or a robot standing at
its start, and prints the mean disturbance metrics (``docs/reaction.md``, "Disturbance metrics"). The variants
switch the robot's influence off while leaving the trigger as it is, so people still react when the robot comes
near, but nothing pushes them:

- ``sf``: ``social_force``, defaults;
- ``sf-no-robot-force``: ``sf_robot_potential_m2ps2 = 0``: the robot exerts no force;
- ``sf-no-force``: also ``sf_repulsion_mps2 = 0``: no force between pedestrians either, only the relaxation
  towards the preferred velocity and the bounds;
- ``sf-no-force-no-lag``: also ``sf_relaxation_time_s`` = the physics substep, so one Euler step reaches the
  preferred velocity (no relaxation lag): what is left is the acceleration and speed bounds;
- ``orca``: defaults;
- ``orca-robot-invisible``: ORCA with the robot moved out of every pedestrian's neighbourhood (a subclass of
  :class:`~envs.reaction.orca.OrcaCrowd` installed for this run only: ORCA has no parameter for it).

Episodes differ between variants (the planner sees where people are; a robot nobody avoids collides more and ends
its episode sooner), so compare the outcomes too. ``--set`` adds reaction parameters to every variant (e.g.
``--set max_accel_mps2=100`` lifts the acceleration bound). Prints a Markdown table; never asserts.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import time
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from agents.evaluation.run import evaluation_env_kwargs
from agents.rollout import DISTURBANCE_METRICS, evaluation_seeds, run_episodes
from agents.runs import load_policy
from envs.config import config_from

#: variant -> (reaction, reaction_params overrides, robot invisible to ORCA)
VARIANTS: dict[str, tuple[str, dict[str, float], bool]] = {
    "sf": ("social_force", {}, False),
    "sf-no-robot-force": ("social_force", {"sf_robot_potential_m2ps2": 0.0}, False),
    "sf-no-force": ("social_force", {"sf_robot_potential_m2ps2": 0.0, "sf_repulsion_mps2": 0.0}, False),
    "sf-no-force-no-lag": (
        "social_force",
        {"sf_robot_potential_m2ps2": 0.0, "sf_repulsion_mps2": 0.0, "sf_relaxation_time_s": None},  # None: substep
        False,
    ),
    "orca": ("orca", {}, False),
    "orca-robot-invisible": ("orca", {}, True),
}


class StandStill:
    """A robot that stays at its start: action 0 (velocity 0; for a unicycle, speed 0 and no turn)."""

    def predict(
        self, obs: Mapping[str, np.ndarray], state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        n = len(next(iter(obs.values())))
        return np.zeros((n, 2), dtype=np.float32), None


@contextlib.contextmanager
def robot_invisible_to_orca() -> Iterator[None]:
    """While open, crowds made for ``reaction="orca"`` see the robot 1000 km away, at rest (out of every pedestrian's
    ``neighbor_distance_m``); the trigger and the release still use its true position."""
    import envs.reaction.orca as orca

    base = orca.OrcaCrowd

    class InvisibleRobotOrca(base):  # type: ignore[misc, valid-type]
        def _model_velocities(self, hood):
            far = dataclasses.replace(hood, robot=hood.robot + 1e6, robot_velocity=np.zeros(2))
            return super()._model_velocities(far)

    orca.OrcaCrowd = InvisibleRobotOrca
    try:
        yield
    finally:
        orca.OrcaCrowd = base


def measure(
    policy_name: str,
    variant: str,
    split: str,
    episodes: int,
    extra: Mapping[str, float] | None = None,
    n_envs: int = 4,
) -> dict[str, Any]:
    """The mean disturbance metrics (and outcomes) of ``episodes`` evaluation episodes of one policy and variant,
    with the reaction parameters ``extra`` on top of the variant's."""
    from envs.crowd_nav import CrowdNavEnv

    reaction, overrides, invisible = VARIANTS[variant]
    kwargs = evaluation_env_kwargs("planner", "none", split, {"reaction": reaction})
    cfg = config_from(kwargs, {})
    params = {k: (cfg.dt_s / cfg.substeps if v is None else v) for k, v in {**overrides, **dict(extra or {})}.items()}
    kwargs["reaction_params"] = params
    cfg = config_from(kwargs, {})
    policy = load_policy("planner", cfg) if policy_name == "planner" else StandStill()
    started = time.process_time()
    with robot_invisible_to_orca() if invisible else contextlib.nullcontext():
        envs = [CrowdNavEnv(**kwargs) for _ in range(n_envs)]
        try:
            rows = run_episodes(policy, envs, evaluation_seeds(split, episodes, 0))
        finally:
            for env in envs:
                env.close()
    out: dict[str, Any] = {"policy": policy_name, "variant": variant, "params": params, "episodes": len(rows)}
    out["disturbed_pct"] = 100.0 * float(np.mean([float(r["ped_disturbed"]) > 0 for r in rows]))
    for key in (*DISTURBANCE_METRICS, "navigation_time_s"):
        out[key] = float(np.mean([float(r[key]) for r in rows]))
    out["outcomes"] = {o: sum(r["outcome"] == o for r in rows) for o in sorted({r["outcome"] for r in rows})}
    out["cpu_s"] = time.process_time() - started
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="univ", help="whose held-out scene")
    p.add_argument("--episodes", type=int, default=60, help="the first N of the evaluation's episode list (seed 0)")
    p.add_argument("--policies", nargs="+", default=["planner", "still"], choices=["planner", "still"])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="reaction parameters for every variant")
    args = p.parse_args()
    extra: dict[str, float] = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            p.error(f"--set takes KEY=VALUE, got {item!r}")
        extra[key] = int(value) if value.lstrip("+-").isdigit() else float(value)  # orca_max_neighbors is an int
    print(f"{args.split}, first {args.episodes} episodes of the evaluation list (seed 0); means per episode", end="")
    print(f"; every variant with {extra}\n" if extra else "\n")
    print(
        "| policy | variant | disturbed % | pedestrians | deviation mean m | deviation max m | delay s "
        "| navigation s | outcomes | CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for policy in args.policies:
        for variant in args.variants:
            r = measure(policy, variant, args.split, args.episodes, extra)
            outcomes = ", ".join(f"{k} {v}" for k, v in r["outcomes"].items())
            print(
                f"| {policy} | {variant} | {r['disturbed_pct']:.0f} | {r['ped_disturbed']:.2f} "
                f"| {r['ped_deviation_mean_m']:.3f} | {r['ped_deviation_max_m']:.3f} | {r['ped_delay_s']:.2f} "
                f"| {r['navigation_time_s']:.1f} | {outcomes} | {r['cpu_s']:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
