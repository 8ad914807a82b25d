"""The privileged reactive ceiling (``make_planner("privileged", reactive=True)``): its plan is the episode, bit for
bit; it keeps clear; it refuses what it cannot plan; it is deterministic; the grid and the command line build it."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agents.ablation as ab
from agents.evaluation.cli import main
from agents.planners import (
    PrivilegedPlanner,
    ReactivePrivilegedPlanner,
    command_velocities,
    env_velocities,
    make_planner,
)
from agents.rollout import evaluation_seeds
from crowdnav_mesrnn.config import ConfigError
from envs.crowd_nav import CrowdNavEnv
from envs.recordings import scripted_recording
from envs.world import robot_path

MODELS = ("pause", "orca", "social_force")
REPO = Path(__file__).resolve().parents[3]
OPTIONS = {"t0_s": 2.0, "start": (0.0, 0.0), "goal": (8.0, 0.0), "time_limit_s": 16.0}


def meeting_crowd() -> Any:
    """A walker head-on down the robot's straight path from (0, 0) to (8, 0), two crossing it, one overtaking: each
    comes within the reaction models' trigger distance of a robot that drives through."""
    t = np.arange(60)[:, None]
    head_on = np.array([11.0, 0.05]) + t * np.array([-0.48, 0.0])
    crossers = [np.array([x, -3.0 + 0.4 * s]) + t * np.array([0.0, 0.5]) for x, s in ((3.0, 0), (5.5, 2))]
    overtaking = np.array([-1.0, 0.4]) + t * np.array([0.55, 0.0])
    return scripted_recording([head_on, *crossers, overtaking])


def run(env: CrowdNavEnv, planner: Any, options: dict[str, Any] | None = None, seed: int = 0) -> tuple[list, dict]:
    """One episode driven by ``planner``: its actions and the last info."""
    obs, _ = env.reset(seed=seed, options=options)
    actions, done, info = [], False, {}
    while not done:
        action = planner.predict(obs)[0]
        actions.append(action)
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return actions, info


@pytest.mark.parametrize("model", MODELS)
def test_its_plan_is_what_happens_bit_for_bit_and_keeps_clear(model: str) -> None:
    env = CrowdNavEnv(predictor="none", crowd=meeting_crowd(), reaction=model)
    planner = make_planner("privileged", env.config, reactive=True, env=env)
    assert isinstance(planner, ReactivePrivilegedPlanner) and planner.privileged
    obs, _ = env.reset(seed=0, options=OPTIONS)
    plan = planner.plan(env)
    assert plan.reaches_goal and plan.contact_free and plan.start_step == 0
    assert plan.crowd.shape == (len(plan.actions), env.replay.num_pedestrians, 2)
    done, k, info = False, 0, {}
    while not done:
        action, state = planner.predict(obs)
        assert state is None and action.dtype == np.float32 and action.shape == (2,)
        np.testing.assert_array_equal(action, plan.actions[k])  # followed, not replanned
        obs, _, terminated, truncated, info = env.step(action)
        # the robot and every pedestrian where the plan's roll-out put them, bit for bit
        np.testing.assert_array_equal(env.robot_position, plan.positions[k + 1])
        positions, present = env.pedestrians
        np.testing.assert_array_equal(present, plan.present[k])
        np.testing.assert_array_equal(positions[present], plan.crowd[k][present])
        k += 1
        done = terminated or truncated
    metrics = info["episode_metrics"]
    assert metrics["outcome"] == "success" and k == len(plan.actions)
    assert metrics["min_gap_m"] >= 0.0 and metrics["ped_disturbed"] > 0  # somebody reacted to the robot
    assert planner.stats.plans == 2 and planner.stats.found == 2 and planner.stats.escapes == 0


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
def test_no_collision_in_replayed_episodes_whose_plans_are_contact_free(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="none", split="zara1", part="test", reaction="orca", data_dir=str(data_dir))
    planner = make_planner("privileged", env.config, reactive=True, env=env)
    for seed in evaluation_seeds("zara1", 3, seed=11):
        escapes = planner.stats.escapes
        _, info = run(env, planner, {"time_limit_s": 8.0}, seed=seed)
        if planner.stats.escapes == escapes:
            assert info["episode_metrics"]["outcome"] != "collision", seed


def test_the_same_episode_twice_gives_the_same_actions() -> None:
    env = CrowdNavEnv(predictor="none", crowd=meeting_crowd(), reaction="social_force")
    first, _ = run(env, make_planner("privileged", env.config, reactive=True, env=env), OPTIONS)
    second, _ = run(env, make_planner("privileged", env.config, reactive=True, env=env), OPTIONS)
    np.testing.assert_array_equal(np.stack(first), np.stack(second))
    planner = make_planner("privileged", env.config, reactive=True, env=env, beam=2, wide_beam=2)
    narrow, _ = run(env, planner, OPTIONS)
    again, _ = run(env, planner, OPTIONS)  # the same planner, its plans of the last episode kept
    np.testing.assert_array_equal(np.stack(narrow), np.stack(again))


def test_it_commands_the_velocities_the_environment_executes() -> None:
    """The float32 action's velocity, capped as env.step caps it, in the environment's floats: numpy's norm differs
    from the environment's in the last bit for some actions, env_velocities never."""
    env = CrowdNavEnv(predictor="none", crowd="empty")
    env.reset(seed=0, options={"start": (0.0, 0.0), "goal": (40.0, 0.0), "time_limit_s": 60.0})
    v, s = env.config.robot_pref_speed_mps, env.config.substeps
    angles = np.random.default_rng(0).uniform(-math.pi, math.pi, 4000)
    actions = np.clip(np.stack([np.cos(angles), np.sin(angles)], axis=1), -1, 1).astype(np.float32)
    exact = env_velocities(actions, v)
    _, numpy_norm = command_velocities(actions.astype(np.float64) * v, v)
    differs = np.flatnonzero((exact != numpy_norm).any(axis=1))
    assert len(differs)  # the case env_velocities exists for
    for i in [*differs[:20].tolist(), 0, 1, 2]:
        start = env.robot_position
        env.step(actions[i])
        expected = robot_path(start, [tuple(exact[i])] * s, env.config.dt_s / s)[-1]  # the world's substeps
        np.testing.assert_array_equal(env.robot_position, expected)


def test_it_refuses_the_replay_unicycles_and_bad_options() -> None:
    with pytest.raises(ValueError, match=r"reaction is 'none'.*make_planner\('privileged'\)"):
        make_planner("privileged", None, reactive=True)
    with pytest.raises(ValueError, match=r"holonomic.*'unicycle'"):
        make_planner("privileged", {"reaction": "orca", "kinematics": "unicycle"}, reactive=True)
    planner = make_planner("privileged", {"reaction": "pause"}, reactive=True)
    replay = CrowdNavEnv(predictor="none", crowd="empty")
    with pytest.raises(ValueError, match="'none'"):
        planner.bind_envs([replay])
    assert isinstance(make_planner("privileged", None, reactive=False), PrivilegedPlanner)
    orca = {"reaction": "orca"}
    for options, words in (
        ({"reactive": "yes"}, ["'reactive'", "'yes'", "true or false"]),
        ({"reactive": True, "beam": 0}, ["'beam'", "0", "integer >= 1"]),
        ({"reactive": True, "beam": 8, "wide_beam": 4}, ["'wide_beam'", "4", ">= beam"]),
        ({"reactive": True, "horizon_steps": 2.5}, ["'horizon_steps'", "2.5", "integer"]),
        ({"reactive": True, "cell_m": 0.0}, ["'cell_m'", "0.0", "> 0"]),
        ({"reactive": True, "margin_m": -0.1}, ["'margin_m'", "-0.1", ">= 0"]),
        ({"reactive": True, "speed_fractions": [1.5]}, ["'speed_fractions'", "1.5", "(0, 1]"]),
        ({"reactive": True, "max_states": 10}, ["'max_states'", "10", "beam, wide_beam"]),
    ):
        with pytest.raises(ValueError) as err:
            make_planner("privileged", orca, **options)
        for word in words:
            assert word in str(err.value), (options, str(err.value))


def test_the_grid_builds_it_from_an_entry_and_refuses_it_on_the_replay(tmp_path: Path) -> None:
    cfg = ab.load_config(REPO / "configs/ablation/reactive.yaml")
    for reaction in MODELS:
        policy = cfg.policy(f"privileged@{reaction}")
        assert policy.kind == "privileged" and dict(policy.options) == {"reactive": True}
        assert cfg.reaction(policy) == reaction and policy.arms == ("oracle",) and policy.priority == 4
    raw: dict[str, Any] = {
        "name": "tiny",
        "runs_dir": str(tmp_path / "runs"),
        "out_dir": str(tmp_path / "results"),
        "splits": ["zara1"],
        "arms": ["none", "oracle"],
        "seeds": [0],
        "policies": {
            "search@orca": {"kind": "search", "env": {"reaction": "orca"}},
            "privileged@orca": {"kind": "privileged", "env": {"reaction": "orca"}, "options": {"reactive": True}},
        },
        "evaluation": {"episodes": 4, "seed": 0},
    }
    assert ab.config_from_mapping(raw).policy("privileged@orca").options == {"reactive": True}
    raw["policies"]["privileged@none"] = {
        "kind": "privileged",
        "env": {"reaction": "none"},
        "options": {"reactive": True},
    }
    with pytest.raises(ConfigError) as err:
        ab.config_from_mapping(raw)
    assert "'policies.privileged@none.options'" in str(err.value) and "reaction is 'none'" in str(err.value)


def test_the_command_line_builds_it_and_labels_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["privileged", "--predictor", "none", "--episodes", "1", "--n-envs", "1", "--set", "crowd=synthetic"]
    assert main([*base, "--set", "reaction=orca", "--planner-set", "reactive=true", "--out", str(tmp_path)]) == 0
    assert "rolls the reaction model forward" in capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["privileged"] is True and summary["planner"] == {"reactive": True}
    assert summary["env"]["reaction"] == "orca"
    assert main([*base, "--planner-set", "reactive=true", "--out", str(tmp_path / "replay")]) != 0
    assert "reaction is 'none'" in capsys.readouterr().err and not (tmp_path / "replay").exists()
