"""What the robot perceives at t depends only on annotations at or before t, on every scene and forecast arm, with
pedestrians replayed or reacting to the robot."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.data import load_recording
from crowdnav_mesrnn.data.recordings import Recording
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.window import PredictorForecast

#: one recording per scene: eth, hotel, univ, zara1, zara2
SCENES = ("biwi_eth", "biwi_hotel", "students003", "crowds_zara01", "crowds_zara02")
ARMS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("none", {}),
    ("cv", {}),
    ("mesrnn", {}),  # the default path: chunks of frames, disk cache
    ("mesrnn", {"cache_forecasts": False}),
    ("mesrnn", {"forecast_memory": "carried"}),
    # pedestrians who react: observed positions and forecasts from the reacted annotations
    ("cv", {"reaction": "orca"}),
    ("mesrnn", {"reaction": "orca"}),
    ("none", {"reaction": "pause"}),
)


def busy_slice(rec: Recording, frames: int = 60) -> Recording:
    """``frames`` annotations around the busiest one (times restart at 0; gaps kept), same name."""
    centre = int(np.argmax(rec.present.sum(axis=1)[20:-40])) + 20
    a = centre - 25
    rows = slice(a, a + frames)
    cols = np.flatnonzero(rec.present[rows].any(axis=0))
    return replace(
        rec, frames=rec.frames[rows], ped_ids=rec.ped_ids[cols], positions=rec.positions[rows][:, cols],
        present=rec.present[rows][:, cols],
    )  # fmt: skip


def perturbed_after(rec: Recording, t_s: float, seed: int = 0) -> Recording:
    """A copy with every annotation after ``t_s`` changed: positions moved, some pedestrians removed or added."""
    rng = np.random.default_rng(seed)
    later = rec.times_s() > t_s + 1e-9
    positions, present = rec.positions.copy(), rec.present.copy()
    positions[later] += rng.normal(0.0, 0.5, size=positions[later].shape)
    flip = rng.random(present[later].shape) < 0.15
    present[later] = present[later] ^ flip
    return replace(rec, positions=positions, present=present)


def observations(env: CrowdNavEnv, options: dict[str, Any], actions: np.ndarray) -> list[tuple[float, dict]]:
    obs, _ = env.reset(seed=0, options=options)
    out = [(env.time_s, obs)]
    for a in actions:
        obs, *_ = env.step(a)
        out.append((env.time_s, obs))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENES)
def test_observations_up_to_t_ignore_annotations_after_t(data_dir: Path, name: str) -> None:
    rec = busy_slice(load_recording(name, data_dir=data_dir))
    times = rec.times_s()
    t0 = round(times[12] / 0.4) * 0.4
    centre = rec.positions[12][rec.present[12]].mean(axis=0)
    start, goal = centre + np.array([-4.0, 1.0]), centre + np.array([4.0, 1.0])
    options = {"t0_s": t0, "start": start, "goal": goal, "time_limit_s": 6.0}
    actions = np.random.default_rng(1).uniform(-0.3, 0.3, size=(12, 2)).astype(np.float32)
    cut = t0 + 3.2  # on biwi_eth between two annotations
    assert np.abs(times - cut).min() > 1e-3 if rec.step_s != 0.4 else np.abs(times - cut).min() < 1e-6
    changed = perturbed_after(rec, cut)
    for predictor, kwargs in ARMS:
        if kwargs.get("forecast_memory") == "carried" and name != "biwi_eth":
            continue
        common = {"predictor": predictor, "terminate_on_collision": False, **kwargs}
        env = CrowdNavEnv(crowd=rec, **common)
        a = observations(env, options, actions)
        b = observations(CrowdNavEnv(crowd=changed, **common), options, actions)
        if kwargs.get("reaction") == "orca":  # people reacted before the cut: the record being tested is not the file
            observed = env._reactive.observed
            assert observed.deviated[observed.times <= cut + 1e-9].any(), (name, predictor)
        compared = seen = 0
        differs = False
        for (ta, oa), (tb, ob) in zip(a, b, strict=True):
            assert ta == tb
            if ta <= cut + 1e-9:
                for key in oa:
                    np.testing.assert_array_equal(oa[key], ob[key], err_msg=f"{name} {predictor} {key} t={ta:.2f}")
                compared += 1
                seen += int(oa["mask"].sum())
            else:
                differs |= any(not np.array_equal(oa[k], ob[k]) for k in oa)
        assert compared == 9 and seen > 9, (name, predictor, seen)
        assert differs, f"{name} {predictor}: the perturbation changed nothing after the cut"


def test_perception_age_is_observed_on_request() -> None:
    from envs.recordings import scripted_recording

    crowd = scripted_recording([np.tile([3.0, 0.0], (60, 1))], step_s=2 / 3)
    env = CrowdNavEnv(predictor="cv", crowd=crowd, observe_perception_age=True, observe_time_left=True)
    assert env.observation_space["robot"].shape == (6,)
    obs, _ = env.reset(seed=0, options={"t0_s": 8.0, "start": (0.0, 0.0), "goal": (0.0, -8.0)})
    ages = [obs["robot"][5]]
    for _ in range(5):
        obs, *_ = env.step(np.zeros(2, dtype=np.float32))
        assert obs in env.observation_space
        ages.append(obs["robot"][5])
    t = 8.0 + 0.4 * np.arange(6)
    np.testing.assert_allclose(ages, t - np.floor(t / (2 / 3) + 1e-9) * (2 / 3), atol=1e-6)
    assert max(ages) > 0.5


def truncated_after(rec: Recording, t_s: float) -> Recording:
    """A copy without any annotation after ``t_s`` (the recording ends at ``t_s``)."""
    keep = rec.times_s() <= t_s + 1e-9
    cols = np.flatnonzero(rec.present[keep].any(axis=0))
    return replace(
        rec, frames=rec.frames[keep], ped_ids=rec.ped_ids[cols], positions=rec.positions[keep][:, cols],
        present=rec.present[keep][:, cols],
    )  # fmt: skip


@pytest.mark.slow
def test_cached_learned_forecasts_ignore_later_frames_of_their_chunk(data_dir: Path) -> None:
    """The default path (forecasts computed per chunk of frames in batched passes) gives, at a frame, exactly what
    that frame alone gives: a crowded frame later in the same chunk must not change the padding of earlier ones
    (on students001 a wider padding moved forecasts by up to 1e-5 m, so data after t changed the observation)."""
    rec = busy_slice(load_recording("students001", data_dir=data_dir), frames=80)
    cut = float(rec.times_s()[16])
    cached = CrowdNavEnv(crowd=rec, predictor="mesrnn", forecast_disk_cache=False).forecaster
    cut_short = CrowdNavEnv(crowd=truncated_after(rec, cut), predictor="mesrnn", forecast_disk_cache=False).forecaster
    single = CrowdNavEnv(crowd=rec, predictor="mesrnn", cache_forecasts=False).forecaster
    assert isinstance(cached, PredictorForecast) and isinstance(cut_short, PredictorForecast)
    assert isinstance(single, PredictorForecast)
    short = truncated_after(rec, cut)
    for i in range(17):
        cols, fc = cached.frame_forecasts(rec, i)
        np.testing.assert_array_equal(fc, single.frame_forecasts(rec, i)[1], err_msg=f"frame {i}: batched vs alone")
        short_cols, short_fc = cut_short.frame_forecasts(short, i)
        np.testing.assert_array_equal(rec.ped_ids[cols], short.ped_ids[short_cols])
        np.testing.assert_array_equal(fc, short_fc, err_msg=f"frame {i}: depends on frames after it")
