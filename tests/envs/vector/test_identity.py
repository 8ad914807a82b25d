"""The batched environment is the single environment, batched: for the same seeds and actions, its observations,
rewards, terminations, truncations and infos equal SyncVectorEnv's over single environments, bit for bit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import SyncVectorEnv

import crowdnav_mesrnn  # noqa: F401 (registers the ids)
from envs.crowd_nav import CrowdNavEnv
from envs.crowds import scripted_recording
from envs.vector import BatchedCrowdNavEnv
from tests.envs.conftest import go_to_goal
from tests.envs.vector.conftest import assert_same_info


def _goal_seeking(kwargs: dict[str, Any]) -> Any:
    from envs.config import CrowdNavConfig

    cfg = CrowdNavConfig(**{k: v for k, v in kwargs.items() if k in ("kinematics",)})
    return lambda i, obs, rng: go_to_goal(obs, cfg) if i % 2 else rng.uniform(-1, 1, 2).astype(np.float32)


@pytest.mark.parametrize("num_envs", [1, 3, 8])
@pytest.mark.parametrize("predictor", ["none", "cv", "oracle", "noisy_oracle"])
def test_every_arm_gives_the_episodes_of_single_envs(
    predictor: str, num_envs: int, data_dir: Path, side_by_side: Any
) -> None:
    kwargs = {"predictor": predictor, "split": "zara1", "part": "test"}
    counts = side_by_side(num_envs, kwargs, steps=120 if num_envs < 8 else 90, seed=num_envs)
    assert counts["ended"] >= num_envs  # autoresets were compared
    # the added metrics were compared where they are not trivial (a minimum time to collision, an acceleration)
    assert counts["ttc_finite"] >= 1 and counts["accel"] == counts["ended"]
    if predictor != "none":
        assert counts["forecast_rows"] > 0


def test_pop_in_events_collisions_and_timeouts_across_autoresets(data_dir: Path, side_by_side: Any) -> None:
    # seed 3, 3 worlds, 200 random steps on zara1: collisions, timeouts and a pop-in event (measured)
    counts = side_by_side(3, {"predictor": "cv", "split": "zara1", "part": "test"}, steps=200, seed=0)
    assert counts["popin_events"] >= 1 and counts["collisions"] >= 1 and counts["ended"] >= 6
    assert counts["ttc_finite"] >= 1


@pytest.mark.parametrize("memory", ["window", "carried"])
def test_learned_forecasts_on_a_short_recording(memory: str, tiny_learned_predictor: Any, side_by_side: Any) -> None:
    # a learned (structural RNN) predictor object on the synthetic crowd: its forecasts go through the window (or
    # carried) source's cache like MESRNN's
    kwargs = {
        "predictor": tiny_learned_predictor(),
        "crowd": "synthetic",
        "synthetic_duration_s": 60.0,
        "forecast_memory": memory,
    }
    counts = side_by_side(3, kwargs, steps=60, seed=5)
    assert counts["forecast_rows"] > 0 and counts["ended"] >= 1


@pytest.mark.slow
def test_mesrnn_forecasts(data_dir: Path, side_by_side: Any) -> None:
    kwargs = {"predictor": "mesrnn", "split": "zara1", "part": "test"}
    counts = side_by_side(3, kwargs, steps=60, seed=2)
    assert counts["forecast_rows"] > 0


@pytest.mark.parametrize(
    "extra",
    [
        {"kinematics": "unicycle", "observe_time_left": True},
        {"terminate_on_collision": False, "observe_perception_age": True, "flatten_observation": False},
        {"part": "train", "episode_time": "val", "intrusion_penalty": -0.5, "time_penalty": -0.01},
    ],
    ids=["unicycle", "no-termination", "train-recordings"],
)
def test_settings(extra: dict[str, Any], data_dir: Path, side_by_side: Any) -> None:
    kwargs = {"predictor": "oracle", "split": "zara1", "part": "test", **extra}
    counts = side_by_side(3, kwargs, steps=100, seed=4, policy=_goal_seeking(extra), reset_every=45)
    assert counts["steps"] == 100


def test_sampled_futures_and_online_regions(data_dir: Path, side_by_side: Any) -> None:
    # the samples are seeded by recording and time, the online tracker restarts with every world's episode
    kwargs = {"predictor": "cv_gaussian", "split": "hotel", "part": "test", "forecast_samples": 4}
    kwargs.update(forecast_uncertainty=True, forecast_uncertainty_method="online")
    counts = side_by_side(3, kwargs, steps=80, seed=5, reset_every=35)
    assert counts["forecast_rows"] > 0


def test_reaction_none_with_parameters_and_a_goal_tolerance(data_dir: Path, side_by_side: Any) -> None:
    # reaction "none" with parameters set: the reset info echoes them (resolved), as the single env's; a wider goal
    # tolerance changes the distance required (path_ratio_required, spl) and goal-seeking worlds succeed
    extra = {"reaction": "none", "reaction_params": {"trigger_distance_m": 2.0}, "goal_tolerance_m": 0.6}
    kwargs = {"predictor": "cv", "split": "zara1", "part": "test", **extra}
    counts = side_by_side(4, kwargs, steps=120, seed=6, policy=_goal_seeking(extra))
    assert counts["spl"] >= 1
    env = BatchedCrowdNavEnv(num_envs=2, **kwargs)
    _, info = env.reset(seed=0)
    assert info["reaction"].tolist() == ["none", "none"]
    assert info["reaction_params"]["trigger_distance_m"].tolist() == [2.0, 2.0]


def _walk(start: tuple[float, float], velocity: tuple[float, float], steps: int, step_s: float) -> np.ndarray:
    return np.asarray(start) + np.arange(steps)[:, None] * np.asarray(velocity) * step_s


@pytest.mark.parametrize("step_s", [0.4, 2 / 3], ids=["0.4s", "biwi-eth-0.667s"])
def test_scripted_pop_ins_and_contacts(step_s: float, side_by_side: Any) -> None:
    # tracks beginning on the standing robot (ghosts), walking into it (contacts), annotations between control steps
    tracks = [
        _walk((0.0, 0.1), (0.0, 1.0), 20, step_s),
        _walk((1.5, 0.0), (-1.2, 0.0), 20, step_s),
        _walk((-0.3, 0.2), (0.3, 0.0), 20, step_s),
        _walk((4.0, 4.0), (0.0, -1.0), 20, step_s),
    ]
    crowd = scripted_recording(tracks, start_steps=[10, 12, 9, 8], num_steps=40, step_s=step_s, name="popins")
    options = {"t0_s": 3.2 if step_s == 0.4 else 6.0, "start": (0.0, 0.0), "goal": (10.0, 0.0), "time_limit_s": 4.0}
    for terminate in (True, False):
        kwargs = {"predictor": "oracle", "crowd": crowd, "terminate_on_collision": terminate}
        counts = side_by_side(
            3, kwargs, steps=30, options=options, policy=lambda i, obs, rng: np.array([0.1 * i, 0.0], np.float32)
        )
        assert counts["popin_events"] >= 3


def test_max_episode_steps_truncates_as_gymnasiums_time_limit(data_dir: Path, side_by_side: Any) -> None:
    # 20 steps: shorter than most episodes (truncated by the limit, no episode metrics), longer than a few (ended by
    # the environment itself, with its metrics): seed 3 gives both (measured: 19 and 4), and autoresets after each
    counts = side_by_side(3, {"predictor": "cv", "split": "zara1", "part": "test"}, steps=150, seed=3,
                          max_episode_steps=20)  # fmt: skip
    assert counts["limited"] >= 3 and counts["ended"] >= 1


def test_make_vec_applies_max_episode_steps_in_both_modes(data_dir: Path) -> None:
    ends = {}
    for mode in ("vector_entry_point", "sync"):
        envs = gymnasium.make_vec(
            "CrowdNav-CV-v0", num_envs=2, vectorization_mode=mode, max_episode_steps=5, split="zara1", part="test"
        )
        envs.reset(seed=0)
        flags = [envs.step(np.zeros((2, 2), np.float32))[3].tolist() for _ in range(5)]
        ends[mode] = flags
        envs.close()
    assert ends["vector_entry_point"] == ends["sync"] == [[False, False]] * 4 + [[True, True]]
    with pytest.warns(UserWarning, match="SyncVectorEnv"):  # the fallback to single environments applies it too
        envs = gymnasium.make_vec(
            "CrowdNav-NoPred-v0", num_envs=2, max_episode_steps=3, crowd="empty", reaction="pause"
        )
    envs.reset(seed=0)
    assert [envs.step(np.zeros((2, 2), np.float32))[3].tolist() for _ in range(3)][-1] == [True, True]
    envs.close()


@pytest.mark.parametrize("value", [0, -1, 2.5, "9", True])
def test_a_bad_max_episode_steps_is_refused_naming_it(value: Any) -> None:
    with pytest.raises(ValueError, match=rf"max_episode_steps must be None or an integer >= 1.*{value!r}"):
        BatchedCrowdNavEnv(num_envs=2, predictor="none", crowd="empty", max_episode_steps=value)


def test_the_action_of_a_world_being_reset_is_ignored_as_sync_vector_env_ignores_it(data_dir: Path) -> None:
    kwargs = {"predictor": "none", "split": "zara1", "part": "test", "max_episode_steps": 2}
    sync = gymnasium.make_vec("CrowdNav-NoPred-v0", num_envs=2, vectorization_mode="sync", **kwargs)
    batched = BatchedCrowdNavEnv(num_envs=2, **kwargs)
    for envs in (sync, batched):
        envs.reset(seed=0)
    still = np.zeros((2, 2), np.float32)
    for _ in range(2):  # both worlds end at the limit
        out = [envs.step(still) for envs in (sync, batched)]
    assert out[0][3].tolist() == out[1][3].tolist() == [True, True]
    nan_actions = np.full((2, 2), np.nan, np.float32)  # the autoreset step: both worlds are reset
    after = [envs.step(nan_actions) for envs in (sync, batched)]
    for key in after[0][0]:
        np.testing.assert_array_equal(after[1][0][key], after[0][0][key])
    with pytest.raises(ValueError, match="action of world 0 must be finite"):  # stepping again: refused
        batched.step(nan_actions)
    sync.close()
    batched.close()


def test_seeds_and_generators_are_each_worlds_as_sync_vector_envs_are() -> None:
    sync = gymnasium.make_vec("CrowdNav-NoPred-v0", num_envs=3, vectorization_mode="sync", crowd="empty")
    batched = BatchedCrowdNavEnv(num_envs=3, predictor="none", crowd="empty")
    assert batched.np_random_seed == (None, None, None)
    for seed in (5, [7, None, 9]):
        for envs in (sync, batched):
            envs.reset(seed=seed)
        assert batched.np_random_seed == sync.np_random_seed
        states = [[g.bit_generator.state for g in envs.np_random] for envs in (sync, batched)]
        assert states[0] == states[1]
    sync.close()
    batched.close()


def test_a_reset_that_fails_for_one_world_leaves_the_others_as_sync_vector_env_does(data_dir: Path) -> None:
    # t0_s = 500 s lies past the end of some of the training recordings: a reset fails at the first world that
    # draws one, after the worlds before it drew theirs. A seeded world's draw depends on its seed only, so a probe
    # finds a seed whose reset fails after world 0 drew its episode.
    kwargs = {"predictor": "cv", "split": "zara1", "part": "train"}
    options = {"t0_s": 500.0}
    probe = BatchedCrowdNavEnv(num_envs=4, **kwargs)
    seed = None
    for candidate in range(100, 200):
        try:
            probe.reset(seed=candidate, options=options)
        except ValueError as exc:
            assert "t0_s" in str(exc)
            if probe.episodes[0] is not None and probe.episodes[0].t0_s == 500.0:
                seed = candidate
                break
    probe.close()
    assert seed is not None
    sync = SyncVectorEnv([lambda: CrowdNavEnv(**kwargs) for _ in range(4)])
    batched = BatchedCrowdNavEnv(num_envs=4, **kwargs)
    rng = np.random.default_rng(0)
    for envs in (sync, batched):
        envs.reset(seed=0)
    for _ in range(2):
        actions = rng.uniform(-1, 1, (4, 2)).astype(np.float32)
        out = [envs.step(actions) for envs in (sync, batched)]
        assert not (out[0][2] | out[0][3]).any()  # no autoreset pending at the failing reset
    for envs in (sync, batched):
        with pytest.raises(ValueError, match="t0_s"):
            envs.reset(seed=seed, options=options)
    assert batched.episodes[0].t0_s == 500.0  # world 0 is in its new episode, the others in their old ones
    for t in range(80):  # world 0's new episode and the others' old ones go on as SyncVectorEnv's, to their ends
        actions = rng.uniform(-1, 1, (4, 2)).astype(np.float32)
        out = [envs.step(actions) for envs in (sync, batched)]
        for key in out[0][0]:
            np.testing.assert_array_equal(out[1][0][key], out[0][0][key], err_msg=f"step {t} obs {key}")
        for i in (1, 2, 3):
            np.testing.assert_array_equal(out[1][i], out[0][i], err_msg=f"step {t} output {i}")
        assert_same_info(out[0][4], out[1][4], f"step {t} info")
    sync.close()
    batched.close()


def test_reset_mask_resets_only_the_masked_worlds(data_dir: Path) -> None:
    env = BatchedCrowdNavEnv(num_envs=3, predictor="none", split="zara1", part="test")
    obs, _ = env.reset(seed=0)
    obs2, info = env.reset(seed=[None, 7, None], options={"reset_mask": np.array([False, True, False])})
    single = gymnasium.make("CrowdNav-NoPred-v0", split="zara1", part="test")
    ref, ref_info = single.reset(seed=7)
    for key in obs:
        np.testing.assert_array_equal(obs2[key][[0, 2]], obs[key][[0, 2]])
        np.testing.assert_array_equal(obs2[key][1], ref[key])
    assert info["_recording"].tolist() == [False, True, False] and info["t0_s"][1] == ref_info["t0_s"]


def test_make_vec_with_the_vector_entry_point(data_dir: Path) -> None:
    envs = gymnasium.make_vec(
        "CrowdNav-CV-v0", num_envs=2, vectorization_mode="vector_entry_point", split="zara1", part="test"
    )
    assert isinstance(envs.unwrapped, BatchedCrowdNavEnv)
    assert envs.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    obs, _ = envs.reset(seed=0)
    assert obs["forecasts"].shape[0] == 2 and envs.observation_space.contains(obs)
    obs, reward, *_ = envs.step(envs.action_space.sample())
    assert reward.shape == (2,) and envs.observation_space.contains(obs)
    envs.close()


def test_errors_name_what_is_wrong() -> None:
    with pytest.raises(ValueError, match="num_envs"):
        BatchedCrowdNavEnv(num_envs=0, predictor="none", crowd="empty")
    env = BatchedCrowdNavEnv(num_envs=2, predictor="none", crowd="empty")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 2)))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="world 1"):
        env.step(np.array([[0.0, 0.0], [np.nan, 0.0]]))
    for seed in (1.5, "3", [0], [0, 1.0], [0, True]):
        with pytest.raises(ValueError, match="seed must be None, an int or a sequence of 2 seeds"):
            env.reset(seed=seed)
    for options in ([1], [("t0_s", 1.0)], "t0_s"):
        with pytest.raises(ValueError, match="reset options must be a mapping"):
            env.reset(seed=0, options=options)
    with pytest.raises(ValueError, match="num_envs"):
        BatchedCrowdNavEnv(num_envs=True, predictor="none", crowd="empty")
    with pytest.raises(ValueError, match=r"num_envs must be an integer in \[1, 256\].*got 300.*sync"):
        BatchedCrowdNavEnv(num_envs=300, predictor="none", crowd="empty")
    # more worlds than one space keeps apart: fine where single environments are stepped anyway
    with pytest.warns(UserWarning, match="SyncVectorEnv"):
        envs = gymnasium.make_vec("CrowdNav-NoPred-v0", num_envs=300, crowd="empty", reaction="pause")
    assert isinstance(envs, gymnasium.vector.SyncVectorEnv) and envs.num_envs == 300
    envs.close()


@pytest.mark.parametrize("reaction", ["pause", "orca", "social_force"])
def test_reacting_pedestrians_are_refused_naming_key_value_and_what_to_use(reaction: str) -> None:
    with pytest.raises(NotImplementedError, match=f"'reaction' = '{reaction}'.*SyncVectorEnv"):
        BatchedCrowdNavEnv(num_envs=2, predictor="none", crowd="empty", reaction=reaction)
    # gymnasium.make_vec steps single environments instead, and says so
    with pytest.warns(UserWarning, match=f"'reaction' = '{reaction}'.*SyncVectorEnv"):
        envs = gymnasium.make_vec(
            "CrowdNav-NoPred-v0", num_envs=2, vectorization_mode="vector_entry_point", crowd="empty", reaction=reaction
        )
    assert isinstance(envs, gymnasium.vector.SyncVectorEnv) and envs.num_envs == 2
    assert all(e.unwrapped.reaction == reaction for e in envs.envs)
    envs.reset(seed=0)
    envs.step(envs.action_space.sample())
    envs.close()
    with pytest.raises(NotImplementedError, match=f"'reaction' = '{reaction}'"):  # from a config mapping too
        BatchedCrowdNavEnv(num_envs=2, config={"reaction": reaction}, predictor="none", crowd="empty")


def test_make_vec_renders_through_single_environments_and_says_so() -> None:
    with pytest.raises(NotImplementedError, match="does not render"):
        BatchedCrowdNavEnv(num_envs=2, predictor="none", crowd="empty", render_mode="rgb_array")
    with pytest.warns(UserWarning, match="does not render.*SyncVectorEnv"):
        envs = gymnasium.make_vec("CrowdNav-NoPred-v0", num_envs=2, crowd="empty", render_mode="rgb_array")
    assert isinstance(envs, gymnasium.vector.SyncVectorEnv)
    envs.reset(seed=0)
    frames = envs.render()
    assert len(frames) == 2 and frames[0].ndim == 3
    envs.close()


def test_forecast_errors_equal_where_worlds_share_a_scene(data_dir: Path, side_by_side: Any) -> None:
    """Worlds of one scene asking for the same rounded times: each world keeps its own memo of resampled forecasts
    and weights, as each single environment does, so the episode's forecast ADE equals the single env's to the bit
    (a shared memo gave ``forecast_ade_m`` 1e-13 m apart on eth at step 57)."""
    counts = side_by_side(3, {"predictor": "cv", "split": "eth", "part": "test"}, 120, seed=5, reset_every=35)
    assert counts["ended"] >= 1 and counts["forecast_rows"] > 0
