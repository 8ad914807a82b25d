"""Pedestrians who react, in the environment (``reaction=``): configuration, identity with the replay where nobody
reacts, avoidance, causal perception, forecasts from observed histories, disturbance metrics, roll-outs."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from crowdnav_mesrnn.config import ConfigError
from envs.config import CrowdNavConfig
from envs.crowd_nav import ENV_REVISION, UNDISTURBED, CrowdNavEnv, env_rules
from envs.forecasting.observed import observed_forecasts
from envs.reaction import REACTION_MODELS, ReactionParams
from envs.reactive import ObservedReplay
from envs.recordings import scripted_recording
from envs.replay import Replay

MODELS = tuple(m for m in REACTION_MODELS if m != "none")
#: Keys the reaction adds to what an episode reports (absent before; zero or "none" without a reaction).
ADDED = {"reaction", "reaction_params", "reaction_revision", *UNDISTURBED}
DISTURBANCE = tuple(UNDISTURBED)


def stripped(value: Any) -> Any:
    """``value`` without the keys the reaction adds (recursively), for comparing episodes with ``none``'s."""
    if isinstance(value, dict):
        return {k: stripped(v) for k, v in value.items() if k not in ADDED}
    if isinstance(value, list | tuple):
        return type(value)(stripped(v) for v in value)
    return value


def assert_same(a: Any, b: Any, where: str = "") -> None:
    """Equal, bit for bit (arrays: dtype, shape and values)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        assert a == b, (where, a, b)


def episode(env: CrowdNavEnv, policy: Callable[[dict], np.ndarray], seed: int, options: dict | None = None) -> list:
    """``[(obs, info), (obs, reward, terminated, truncated, info), ...]`` and the world's pedestrians at every step."""
    obs, info = env.reset(seed=seed, options=options)
    out: list = [(obs, info, env.pedestrians, env.last_forecasts)]
    done = False
    while not done:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        out.append((obs, reward, terminated, truncated, info, env.pedestrians, env.last_forecasts))
        done = terminated or truncated
    return out


def standing(obs: dict) -> np.ndarray:
    return np.zeros(2, dtype=np.float32)


def wobbly_line(start: tuple[float, float], velocity: tuple[float, float], steps: int, wobble_m: float = 0.05):
    """A straight walk with a deterministic sideways wobble (annotation noise), annotations every 0.4 s."""
    t = 0.4 * np.arange(steps)
    normal = np.array([-velocity[1], velocity[0]]) / np.hypot(*velocity)
    return np.asarray(start) + np.outer(t, velocity) + wobble_m * np.sin(1.3 * np.arange(steps))[:, None] * normal


def lanes_recording(near: bool = False):
    """Walkers in lanes 4-5.5 m beside the robot's straight 8 m path from (0, 0) to (8, 0) (within the 6 m sensor
    range, beyond the 3 m trigger distance); with ``near``, one more walks head-on down the robot's path."""
    tracks = [
        wobbly_line((-2.0, 4.5), (1.1, 0.0), 50),
        wobbly_line((12.0, -5.0), (-1.2, 0.05), 50),
        wobbly_line((3.0, 5.5), (0.5, 0.1), 50),
        wobbly_line((14.0, 4.0), (-1.0, 0.0), 50),
    ]
    starts = [0, 2, 5, 8]
    if near:
        tracks.append(wobbly_line((11.0, 0.1), (-1.2, 0.0), 50, wobble_m=0.02))
        starts.append(14)
    return scripted_recording(tracks, starts, name="lanes")


LANES_OPTIONS = {"t0_s": 6.0, "start": (0.0, 0.0), "goal": (8.0, 0.0), "time_limit_s": 14.0}


def go_to(cfg: CrowdNavConfig) -> Callable[[dict], np.ndarray]:
    def policy(obs: dict) -> np.ndarray:
        offset = np.asarray(obs["robot"][:2], dtype=np.float64)
        dist = float(np.hypot(*offset))
        speed = min(cfg.robot_pref_speed_mps, dist / cfg.dt_s)
        return (offset / max(dist, 1e-9) * speed / cfg.robot_pref_speed_mps).astype(np.float32)

    return policy


# ---------------------------------------------------------------------------------------------- configuration


def test_reaction_is_configured_named_and_checked(tmp_path: Path) -> None:
    env = CrowdNavEnv(crowd="synthetic", predictor="cv", reaction="orca", reaction_params={"trigger_distance_m": 2})
    assert env.config.reaction == "orca"
    assert env.config.reaction_parameters == ReactionParams(trigger_distance_m=2.0)
    _, info = env.reset(seed=0)
    assert info["reaction"] == "orca" and info["env_revision"] == ENV_REVISION
    assert info["reaction_params"] == ReactionParams(trigger_distance_m=2.0).to_dict()
    assert env_rules(env.config) == {
        "env_revision": ENV_REVISION,
        "reaction": "orca",
        "reaction_params": ReactionParams(trigger_distance_m=2.0).to_dict(),
    }
    # none: the rules of revision 1, nothing added (results under revision 1 stay valid)
    assert env_rules() == {"env_revision": ENV_REVISION} == env_rules({"reaction": "none"})
    plain = CrowdNavEnv(crowd="synthetic", predictor="cv")
    _, info = plain.reset(seed=0)
    assert info["reaction"] == "none" and info["reaction_params"] == ReactionParams().to_dict()
    # YAML
    path = tmp_path / "env.yaml"
    path.write_text("reaction: pause\nreaction_params:\n  pause_margin_m: 0.2\n")
    cfg = CrowdNavEnv(config=str(path), crowd="synthetic", predictor="none").config
    assert cfg.reaction == "pause" and cfg.reaction_params["pause_margin_m"] == 0.2
    # errors name the key, the value and what is allowed
    with pytest.raises(ConfigError, match=r"unknown reaction 'ocra'; valid: none, pause, orca, social_force"):
        CrowdNavEnv(crowd="synthetic", predictor="none", reaction="ocra")
    with pytest.raises(ConfigError, match=r"'trigger_distance_m' must be a finite number > 0, got -1"):
        CrowdNavEnv(crowd="synthetic", predictor="none", reaction="orca", reaction_params={"trigger_distance_m": -1})
    with pytest.raises(ConfigError, match=r"unknown reaction parameter key 'trigger'.*trigger_distance_m"):
        CrowdNavEnv(crowd="synthetic", predictor="none", reaction="orca", reaction_params={"trigger": 1.0})
    with pytest.raises(ConfigError, match="must be a mapping"):
        CrowdNavEnv(crowd="synthetic", predictor="none", reaction_params=3)


def test_carried_forecasts_are_refused_with_a_reaction(tiny_learned_predictor: Callable) -> None:
    with pytest.raises(ConfigError, match="forecast_memory 'window'"):
        CrowdNavEnv(crowd="synthetic", predictor=tiny_learned_predictor(), forecast_memory="carried", reaction="orca")


def test_none_makes_no_crowd_and_has_no_snapshot() -> None:
    env = CrowdNavEnv(crowd=lanes_recording(near=True), predictor="cv")
    env.reset(seed=0, options=LANES_OPTIONS)
    assert env._reactive is None
    with pytest.raises(RuntimeError, match="reaction='none'"):
        env.reaction_snapshot()


# ---------------------------------------------------------------------------------------------- every value, every arm


@pytest.mark.slow  # 3-6 s: the quick suite stays under 5 minutes (README, Development)
@pytest.mark.parametrize("reaction", REACTION_MODELS)
def test_every_reaction_runs_with_every_arm_and_passes_the_checkers(
    reaction: str, data_dir: Path, tiny_learned_predictor: Callable
) -> None:
    arms: list[Any] = ["none", "cv", "oracle", "noisy_oracle", tiny_learned_predictor()]
    for arm in arms:
        env = CrowdNavEnv(predictor=arm, split="univ", part="test", reaction=reaction, data_dir=str(data_dir))
        for seed in range(2):
            steps = episode(env, go_to(env.config), seed, {"time_limit_s": 4.0})
            assert steps[0][1]["reaction"] == reaction
            for step in steps[1:]:
                assert step[0] in env.observation_space
            metrics = steps[-1][4]["episode_metrics"]
            assert set(DISTURBANCE) <= set(metrics)
            if reaction == "none":
                assert all(metrics[k] == 0 for k in DISTURBANCE)
    env = gym.make("CrowdNav-CV-v0", split="univ", part="test", reaction=reaction, data_dir=str(data_dir))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped)
    assert not [str(w.message) for w in caught]


def test_vector_api(data_dir: Path) -> None:
    envs = gym.make_vec(
        "CrowdNav-CV-v0", num_envs=2, vectorization_mode="sync", reaction="orca", split="univ", part="test",
        data_dir=str(data_dir),
    )  # fmt: skip
    obs, info = envs.reset(seed=0)
    assert list(info["reaction"]) == ["orca", "orca"]
    for _ in range(5):
        obs, _, _, _, info = envs.step(np.zeros((2, 2), dtype=np.float32))
    assert obs["robot"].shape[0] == 2
    envs.close()


@pytest.mark.slow
def test_the_issue_example_runs_with_mesrnn(data_dir: Path) -> None:
    env = gym.make("CrowdNav-MESRNN-v0", reaction="orca", split="univ", part="test", data_dir=str(data_dir))
    obs, info = env.reset(seed=0, options={"time_limit_s": 2.0})
    assert info["reaction"] == "orca" and info["predictor"] == "mesrnn"
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(go_to(env.unwrapped.config)(obs))
        done = terminated or truncated
    assert set(DISTURBANCE) <= set(info["episode_metrics"])


# ---------------------------------------------------------------------------------------------- where nobody reacts


@pytest.mark.parametrize("model", MODELS)
def test_a_robot_far_from_everyone_gives_the_replay(model: str, tiny_learned_predictor: Callable) -> None:
    """Walkers within the sensor range and beyond the trigger distance: the episode of every arm is ``none``'s,
    observations, forecasts, rewards and infos bit for bit."""
    crowd = lanes_recording()
    for arm in ("cv", "oracle", "noisy_oracle", tiny_learned_predictor()):
        runs = []
        for reaction in ("none", model):
            env = CrowdNavEnv(crowd=crowd, predictor=arm, reaction=reaction)
            runs.append(episode(env, go_to(env.config), 3, LANES_OPTIONS))
        replay, reacting = runs
        seen = sum(int(step[0]["mask"].sum()) for step in replay)
        assert seen >= 15 and len(replay) > 8  # the walkers are observed, their forecasts compared
        assert_same(stripped(replay), stripped(reacting))
        assert all(reacting[-1][4]["episode_metrics"][k] == 0 for k in DISTURBANCE)


@pytest.mark.parametrize("model", MODELS)
def test_a_pedestrian_never_near_the_robot_moves_as_recorded(model: str) -> None:
    """One walker comes down the robot's path and reacts; the others never come within the trigger distance and stay
    at their recorded positions in the world, bit for bit."""
    env = CrowdNavEnv(crowd=lanes_recording(near=True), predictor="cv", reaction=model, terminate_on_collision=False)
    steps = episode(env, go_to(env.config), 0, LANES_OPTIONS)
    replay = env.replay
    head_on = int(np.flatnonzero(replay.columns == 4)[0])  # the fifth track
    moved = False
    for n, step in enumerate(steps):
        positions, present = step[-2]
        recorded, recorded_present = replay.positions_at(np.array([LANES_OPTIONS["t0_s"] + 0.4 * n]))
        others = np.arange(replay.num_pedestrians) != head_on
        np.testing.assert_array_equal(present[others], recorded_present[0, others])
        np.testing.assert_array_equal(positions[others][present[others]], recorded[0, others][present[others]])
        moved |= bool(present[head_on] and np.any(positions[head_on] != recorded[0, head_on]))
    assert moved
    assert steps[-1][4]["episode_metrics"]["ped_disturbed"] == 1


# ---------------------------------------------------------------------------------------------- people react


@pytest.mark.slow
def test_a_standing_robot_is_avoided_with_orca(data_dir: Path) -> None:
    """A robot standing in univ's crowds: the replay walks into it in many episodes, ORCA pedestrians (almost) never."""
    hits = {}
    for reaction in ("none", "orca"):
        env = CrowdNavEnv(
            predictor="none", split="univ", part="test", reaction=reaction, terminate_on_collision=False,
            data_dir=str(data_dir),
        )  # fmt: skip
        hits[reaction] = 0
        for seed in range(12):
            steps = episode(env, standing, seed, {"time_limit_s": 30.0})
            hits[reaction] += steps[-1][4]["episode_metrics"]["collisions"] > 0
    assert hits["none"] >= 4, hits
    assert hits["orca"] <= hits["none"] // 4, hits


@pytest.mark.parametrize("model", MODELS)
def test_driving_through_people_disturbs_them(model: str) -> None:
    env = CrowdNavEnv(crowd=lanes_recording(near=True), predictor="cv", reaction=model, terminate_on_collision=False)
    metrics = episode(env, go_to(env.config), 0, LANES_OPTIONS)[-1][4]["episode_metrics"]
    assert metrics["ped_disturbed"] == 1
    assert metrics["ped_deviation_max_m"] >= metrics["ped_deviation_mean_m"] > 0.01
    if model == "pause":
        assert metrics["ped_delay_s"] > 0.0


# ---------------------------------------------------------------------------------------------- perception, forecasts


def test_observed_annotations_are_where_people_were(data_dir: Path) -> None:
    """The tracker's record of an episode: recorded annotations where nobody reacted, the world's positions where
    someone did (on 0.4 s scenes every annotation is a control time), and velocities and presence between
    annotations as :class:`~envs.replay.Replay` computes them from those annotations (same floats)."""
    env = CrowdNavEnv(predictor="cv", split="univ", part="test", reaction="orca", data_dir=str(data_dir))
    env.reset(seed=1, options={"time_limit_s": 16.0})
    deviated = 0
    for _ in range(30):
        obs, *_ = env.step(np.zeros(2, dtype=np.float32))
        observed = env._reactive.observed
        i = observed.perceived_at(env.time_s).index
        positions, present = env.pedestrians
        seen = observed.present[i] & present
        np.testing.assert_array_equal(observed.positions[i][seen], positions[seen])
        deviated += bool(observed.deviated[i])
        # what the robot observes: the world's positions of the pedestrians it perceives
        rows = env.observed_rows
        relative = obs["pedestrians"].reshape(-1, 4)[: len(rows), :2]
        np.testing.assert_allclose(relative, positions[rows] - env.robot_position, rtol=0, atol=1e-5)
    assert deviated >= 5
    # the incremental record equals a replay built from the recorded annotations
    rec = env.replay.recording
    frames = np.searchsorted(rec.times_s(), observed.times - 1e-6)
    positions, present = rec.positions.copy(), rec.present.copy()
    positions[frames[:, None], observed.columns[None, :]] = observed.positions
    present[frames[:, None], observed.columns[None, :]] = observed.present
    from dataclasses import replace

    ep, cfg = env.episode, env.config
    history_s = 7 * rec.step_s  # as the environment slices its replay
    rebuilt = Replay(
        replace(rec, positions=positions, present=present),
        ep.t0_s - history_s,
        ep.t0_s + (ep.max_steps + 1 + cfg.horizon_steps) * cfg.dt_s,
    )
    assert np.array_equal(rebuilt.columns, observed.columns) and np.array_equal(rebuilt.times, observed.times)
    for name in ("valid", "slopes", "annotation_velocity", "arrival_velocity"):
        np.testing.assert_array_equal(getattr(rebuilt, name)[:-1], getattr(observed, name)[:-1], err_msg=name)


def test_observed_forecasts_equal_the_cache_on_recorded_histories(data_dir: Path, tiny_learned_predictor) -> None:
    """Fed the recorded histories, the online path gives the cached forecasts bit for bit (social and independent
    predictors); fed reacted histories, it gives others."""
    for arm in ("cv", tiny_learned_predictor()):
        env = CrowdNavEnv(predictor=arm, split="univ", part="test", data_dir=str(data_dir))
        compared = 0
        for seed in range(2):
            obs, _ = env.reset(seed=seed, options={"time_limit_s": 6.0})
            done = False
            while not done:
                rows = env.observed_rows
                if len(rows):
                    online = observed_forecasts(env.forecaster, ObservedReplay(env.replay), env.time_s, rows)
                    np.testing.assert_array_equal(online, env.last_forecasts)
                    compared += len(rows)
                obs, _, terminated, truncated, _ = env.step(go_to(env.config)(obs))
                done = terminated or truncated
        assert compared > 20
    env = CrowdNavEnv(predictor="cv", split="univ", part="test", reaction="orca", data_dir=str(data_dir))
    env.reset(seed=1, options={"time_limit_s": 16.0})
    differs = False
    for _ in range(20):
        env.step(np.zeros(2, dtype=np.float32))
        rows = env.observed_rows
        cached = env.forecaster.forecast(env.replay, env.time_s, rows, None, np.random.default_rng(0))
        differs |= not np.array_equal(cached, env.last_forecasts)
    assert differs


# ---------------------------------------------------------------------------------------------- roll-outs


@pytest.mark.parametrize("model", MODELS)
def test_a_rollout_of_the_executed_path_is_the_episode(model: str, data_dir: Path) -> None:
    """A snapshot rolled forward with the velocities the robot then executes gives the world's pedestrians, bit for
    bit; another path gives another crowd; the environment is untouched by roll-outs."""
    env = CrowdNavEnv(predictor="cv", split="univ", part="test", reaction=model, terminate_on_collision=False,
                      data_dir=str(data_dir))  # fmt: skip
    obs, _ = env.reset(seed=1, options={"time_limit_s": 16.0})
    for _ in range(5):
        obs, *_ = env.step(go_to(env.config)(obs))
    snapshot = env.reaction_snapshot()

    def policy(obs: dict) -> np.ndarray:  # within the unit disk: the velocity is the action, unscaled by the env
        return (0.9 * go_to(env.config)(obs)).astype(np.float32)

    actions = [policy(obs)]
    velocities = []
    expected = []
    other = snapshot.simulate(np.tile([[0.0, -1.0]], (8, 1)))  # before stepping: the env must not move
    for k in range(8):
        velocities.append(np.asarray(actions[-1], dtype=np.float64) * env.config.robot_pref_speed_mps)
        obs, *_ = env.step(actions[-1])
        expected.append(env.pedestrians)
        actions.append(policy(obs) if k % 3 else np.array([0.3, -0.8], dtype=np.float32))
    rollout = snapshot.simulate(np.array(velocities))
    s = env.config.substeps
    for k, (positions, present) in enumerate(expected):
        np.testing.assert_array_equal(rollout.present[(k + 1) * s], present, err_msg=f"step {k}")
        np.testing.assert_array_equal(rollout.positions[(k + 1) * s][present], positions[present], err_msg=f"step {k}")
    assert rollout.reacting.any() or model == "pause"
    assert not np.array_equal(other.positions, rollout.positions)
    # a roll-out continued from where another ended is the whole roll-out (a tree search's expansion)
    head = snapshot.simulate(np.array(velocities[:3]))
    tail = head.end.simulate(np.array(velocities[3:]))
    assert tail.end.time_s == rollout.end.time_s
    np.testing.assert_array_equal(tail.times_s, rollout.times_s[3 * s :])
    np.testing.assert_array_equal(tail.present, rollout.present[3 * s :])
    np.testing.assert_array_equal(tail.positions[tail.present], rollout.positions[3 * s :][tail.present])
