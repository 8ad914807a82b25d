"""The privileged ceiling: it reads the replay (never the observation), plans the whole route, and says so."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.evaluation.cli import main
from agents.evaluation.run import evaluate
from agents.evaluation.summary import ceiling_fraction, format_summary, read_episodes
from agents.planners import PrivilegedPlanner, StraightToGoal, make_planner
from envs.crowd_nav import ENV_REVISION, CrowdNavEnv
from envs.crowds import scripted_recording

HEAD_ON = {"t0_s": 3.2, "start": (0.0, 0.0), "goal": (10.0, 0.0)}


def crossing_crowd() -> object:
    """A head-on walker on the robot's line and a crosser that appears (track begins) 2 m ahead of the robot's
    straight path after 2 s: nothing a causal policy sees at the start."""
    head_on = [(14.0 - 0.48 * k, 0.0) for k in range(60)]
    crosser = [(3.0, -2.0 + 0.4 * k) for k in range(30)]
    return scripted_recording([head_on, crosser], start_steps=[0, 13])


def test_privileged_planner_succeeds_where_straight_collides_and_its_plan_is_what_happens() -> None:
    env = CrowdNavEnv(predictor="none", crowd=crossing_crowd())
    obs, _ = env.reset(seed=0, options=HEAD_ON)
    straight = StraightToGoal(env.config)
    done, info = False, {}
    while not done:
        obs, _, terminated, truncated, info = env.step(straight.predict(obs)[0])
        done = terminated or truncated
    assert info["episode_metrics"]["outcome"] == "collision"

    planner = PrivilegedPlanner(env.config, env=env)
    obs, _ = env.reset(seed=0, options=HEAD_ON)
    plan = planner.plan(env)
    assert plan.reaches_goal and plan.start_step == 0
    done, k = False, 0
    while not done:
        action, state = planner.predict(obs)
        assert state is None and action.dtype == np.float32 and action.shape == (2,)
        np.testing.assert_array_equal(action, plan.actions[k])  # followed, not replanned
        obs, _, terminated, truncated, info = env.step(action)
        k += 1
        np.testing.assert_allclose(env.robot_position, plan.positions[k], rtol=0, atol=1e-12)
        done = terminated or truncated
    assert info["episode_metrics"]["outcome"] == "success" and k == len(plan.actions)
    assert planner.stats.plans == 2 and planner.stats.found == 2  # the test's plan, and the one predict followed


def test_privileged_planner_replans_when_the_robot_is_off_its_plan() -> None:
    env = CrowdNavEnv(predictor="none", crowd=crossing_crowd())
    planner = PrivilegedPlanner(env.config, env=env)
    obs, _ = env.reset(seed=0, options=HEAD_ON)
    planner.predict(obs)
    obs, *_ = env.step(np.array([0.0, 1.0], dtype=np.float32))  # not what the plan said
    planner.predict(obs)
    assert planner.stats.plans == 2


def test_privileged_planner_needs_its_environments_and_holonomic_motion() -> None:
    env = CrowdNavEnv(predictor="none", crowd="empty")
    obs, _ = env.reset(seed=0)
    planner = make_planner("privileged", env.config)
    with pytest.raises(ValueError, match="bind_envs"):
        planner.predict(obs)
    planner.bind_envs([env])
    assert planner.predict(obs)[0].shape == (2,)
    with pytest.raises(ValueError, match="holonomic"):
        PrivilegedPlanner({"kinematics": "unicycle"})


def test_evaluate_labels_the_privileged_ceiling(tmp_path: Path) -> None:
    s = evaluate("privileged", "none", "zara1", 3, out_dir=tmp_path, env_overrides={"crowd": "synthetic"}, n_envs=2)
    assert s["privileged"] is True and s["policy"] == "privileged" and s["success_rate"] == 1.0
    assert s["env_revision"] == ENV_REVISION and s["code_version"]  # which rules and code the result ran under
    assert json.loads((tmp_path / "summary.json").read_text())["privileged"] is True
    assert "PRIVILEGED" in format_summary(s)
    other = evaluate("straight", "none", "zara1", 3, env_overrides={"crowd": "synthetic"}, ceiling=tmp_path)
    assert other["privileged"] is False
    assert other["ceiling"]["episodes"] == 3 and other["ceiling"]["ceiling_success_rate"] == 1.0
    assert other["ceiling"]["fraction"] == pytest.approx(other["success_rate"])


def test_ceiling_fraction_pairs_episodes_by_seed() -> None:
    ceiling = [{"seed": s, "outcome": "success" if s != 3 else "collision"} for s in range(10)]  # 9 of 10
    policy = [{"seed": s, "outcome": "success" if s < 6 else "timeout"} for s in range(12)]  # seeds 10, 11 unpaired
    out = ceiling_fraction(policy, ceiling)
    assert out["episodes"] == 10
    assert out["success_rate"] == pytest.approx(0.6) and out["ceiling_success_rate"] == pytest.approx(0.9)
    assert out["fraction"] == pytest.approx(0.6 / 0.9)
    assert out["success_where_ceiling_succeeds"] == pytest.approx(5 / 9)  # seeds 0-5 minus 3
    lo, hi = out["fraction_ci"]
    assert lo < out["fraction"] < hi
    assert ceiling_fraction(policy, [{"seed": 99, "outcome": "success"}])["fraction"] is None
    moved = [{**r, "recording": "students001"} for r in ceiling]
    with pytest.raises(ValueError, match="different episodes"):
        ceiling_fraction([{**r, "recording": "students003"} for r in policy], moved)


def test_command_line_reports_the_fraction_of_the_ceiling(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["--predictor", "none", "--episodes", "2", "--set", "crowd=synthetic", "--n-envs", "1"]
    assert main(["privileged", *base, "--out", str(tmp_path / "ceiling"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["privileged"] is True
    assert len(read_episodes(tmp_path / "ceiling")) == 2
    assert main(["straight", *base, "--ceiling", str(tmp_path / "ceiling"), "--no-progress"]) == 0
    assert "success / ceiling" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError, match=r"episodes\.csv"):
        read_episodes(tmp_path / "nowhere")
