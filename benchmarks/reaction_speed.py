"""Cost of the reaction models against ``none``, per control step, for crowds of 10 and 30 pedestrians.

Run: ``python benchmarks/reaction_speed.py [--crowds 10 30] [--seconds 30] [--repeats 5]``. A synthetic crowd (made in
code, no data needed) walks to and fro across a 12 m x 12 m square for ``--seconds``, and the robot crosses it
through the middle at 0.4 m/s, so part of the crowd reacts. Each model steps it in two modes: 4 physics substeps of
0.1 s per control step, or 1 step of 0.4 s (the control step; the environment then interpolates the substeps), with
the recorded positions computed beforehand (the environment has them anyway). Printed: the median over repeats of
the process's CPU time per control step (robust to other processes on the cores), the ratio against ``none`` in the
same mode and process, and how many pedestrians react on average per step. Never asserts on time.
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
from _timing import median_seconds

from envs.reaction import REACTION_MODELS, ReactionParams, make_reactive_crowd
from envs.recordings import scripted_recording
from envs.replay import Replay

SUBSTEP_S = 0.1
CONTROL_S = 0.4


def crowd(num: int, seconds: float, seed: int = 0):
    """``num`` pedestrians walking to and fro across a 12 m square (lanes spread over it, 1.0-1.5 m/s, turning back at
    its edges), all present for the whole run: a recording with annotations every 0.4 s."""
    rng = np.random.default_rng(seed)
    t = 0.4 * np.arange(int(seconds / 0.4) + 2)
    trajs = []
    for _ in range(num):
        travel = rng.uniform(0.0, 24.0) + rng.uniform(1.0, 1.5) * t  # along a 24 m loop: out and back
        x = np.abs((travel % 24.0) - 12.0) - 6.0
        trajs.append(np.stack([x, np.full(len(t), rng.uniform(-5.0, 5.0))], axis=1))
    return scripted_recording(trajs, name=f"bench-{num}")


def run(model: str, replay: Replay, step_s: float, rec: np.ndarray, present: np.ndarray, robot: np.ndarray) -> int:
    """One pass over the run in steps of ``step_s``; returns the number of (pedestrian, step) pairs reacting."""
    c = make_reactive_crowd(model, ReactionParams(), robot_radius_m=0.3, pedestrian_radius_m=0.3)
    c.reset(replay, 0.0)
    vel = (robot[1] - robot[0]) / step_s
    reacting = 0
    for k in range(len(rec) - 1):
        out = c.step(c.time_s, step_s, rec[k], present[k], rec[k + 1], present[k + 1], robot[k], vel)
        reacting += int(out.reacting.sum())
    return reacting


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--crowds", type=int, nargs="+", default=[10, 30], help="crowd sizes")
    p.add_argument("--seconds", type=float, default=30.0, help="length of a run")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    print(f"CPU time per control step of {CONTROL_S} s (median of {args.repeats} runs of {args.seconds:g} s); "
          "x none: ratio in the same mode")  # fmt: skip
    print(f"{'crowd':>6}{'model':>14}{'mode':>22}{'us/control step':>17}{'x none':>8}{'reacting':>10}")
    for num in args.crowds:
        replay = Replay(crowd(num, args.seconds))
        for mode, step_s in ((f"4 substeps of {SUBSTEP_S} s", SUBSTEP_S), (f"1 step of {CONTROL_S} s", CONTROL_S)):
            steps = round(args.seconds / step_s)
            times = step_s * np.arange(steps + 1)
            rec, present = replay.positions_at(times)
            robot = np.stack([-6.0 + 12.0 / args.seconds * times, np.zeros_like(times)], axis=1)
            reference = None
            for model in REACTION_MODELS:
                reacting = run(model, replay, step_s, rec, present, robot)
                once = functools.partial(run, model, replay, step_s, rec, present, robot)
                sec = median_seconds(once, args.repeats, clock=time.process_time)
                per_control = 1e6 * sec / steps * CONTROL_S / step_s
                reference = per_control if model == "none" else reference
                assert reference is not None
                print(f"{num:>6}{model:>14}{mode:>22}{per_control:>17.1f}{per_control / reference:>8.1f}"
                      f"{reacting / steps:>10.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
