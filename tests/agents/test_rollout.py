"""Running episodes: the fixed episode list, and lockstep stepping independent of the number of environments."""

from __future__ import annotations

import pytest

from agents.planners import SamplingPlanner
from agents.rollout import evaluation_seeds, run_episodes
from envs.crowd_nav import CrowdNavEnv


def test_evaluation_seeds_are_fixed_nested_and_per_split() -> None:
    a = evaluation_seeds("zara1", 50)
    assert a == evaluation_seeds("zara1", 50) and evaluation_seeds("zara1", 20) == a[:20]
    assert a != evaluation_seeds("univ", 50) and a != evaluation_seeds("zara1", 50, seed=1)
    assert len(set(a)) == 50
    with pytest.raises(ValueError, match="split"):
        evaluation_seeds("zara3", 5)


def test_lockstep_episodes_do_not_depend_on_how_many_envs_run() -> None:
    seeds = evaluation_seeds("zara1", 6)
    results = []
    for n in (1, 3):
        envs = [CrowdNavEnv(predictor="cv", crowd="synthetic", part="test") for _ in range(n)]
        results.append(run_episodes(SamplingPlanner(envs[0].config), envs, seeds))
    assert results[0] == results[1]
    assert [r["seed"] for r in results[0]] == seeds
