"""Helpers of the batched-environment tests: run the batched env and SyncVectorEnv over single envs side by side."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from gymnasium.vector import SyncVectorEnv
from gymnasium.wrappers import TimeLimit

from envs.crowd_nav import UNDISTURBED, CrowdNavEnv
from envs.vector import BatchedCrowdNavEnv


def assert_same_info(a: Any, b: Any, where: str) -> None:
    """``a`` and ``b`` (vector infos) equal: the same keys, arrays of the same dtype and values (NaN equal to NaN)."""
    if isinstance(a, dict):
        assert isinstance(b, dict), where
        assert set(a) == set(b), f"{where}: keys {sorted(set(a) ^ set(b))} differ"
        for key in a:
            assert_same_info(a[key], b[key], f"{where}.{key}")
        return
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
    if a.dtype == object:
        for x, y in zip(a.tolist(), b.tolist(), strict=True):
            assert_same_info(x, y, where) if isinstance(x, dict) else None
            if not isinstance(x, dict):
                assert type(x) is type(y) and (x == y or (x != x and y != y)), f"{where}: {x!r} != {y!r}"
    else:
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), f"{where}: {a} != {b}"


def run_side_by_side(
    num_envs: int,
    kwargs: dict[str, Any],
    steps: int,
    seed: int = 0,
    policy: Callable[[int, dict[str, np.ndarray], np.random.Generator], np.ndarray] | None = None,
    options: dict[str, Any] | None = None,
    reset_every: int = 0,
    max_episode_steps: int | None = None,
) -> dict[str, int]:
    """Step a :class:`BatchedCrowdNavEnv` and a ``SyncVectorEnv`` of ``CrowdNavEnv`` with the same seeds and actions,
    asserting identical outputs at every step (random actions unless ``policy``); ``reset_every`` > 0 also calls a
    seeded ``reset`` every that many steps. Returns counts: episodes ended, collisions, pop-in events, steps, rows of
    forecasts, and episodes whose compared metrics were not trivial: a finite minimum time to collision
    (``ttc_finite``), a non-zero mean acceleration (``accel``), a success (``spl``). Every ended episode's metrics
    also hold the undisturbed disturbance metrics, and every reset info the reaction's name and parameters.
    ``max_episode_steps``: the single environments in Gymnasium's ``TimeLimit``, the batched one given the same limit
    (``limited`` counts the truncations at the limit where the environment did not end the episode itself)."""

    def single() -> Any:
        env = CrowdNavEnv(**kwargs)
        return env if max_episode_steps is None else TimeLimit(env, max_episode_steps)

    sync = SyncVectorEnv([single for _ in range(num_envs)])
    extra = {} if max_episode_steps is None else {"max_episode_steps": max_episode_steps}
    batched = BatchedCrowdNavEnv(num_envs=num_envs, **kwargs, **extra)
    rng = np.random.default_rng(seed)
    counts = {"ended": 0, "collisions": 0, "popin_events": 0, "steps": 0, "forecast_rows": 0, "limited": 0}
    counts.update(ttc_finite=0, accel=0, spl=0)

    def reset(k: int) -> dict[str, np.ndarray]:
        obs_s, info_s = sync.reset(seed=seed + 1000 * k, options=dict(options) if options else None)
        obs_b, info_b = batched.reset(seed=seed + 1000 * k, options=dict(options) if options else None)
        for key in obs_s:
            assert obs_b[key].dtype == obs_s[key].dtype
            np.testing.assert_array_equal(obs_b[key], obs_s[key], err_msg=f"reset obs {key}")
        assert_same_info(info_s, info_b, "reset info")
        assert set(info_b["reaction"].tolist()) == {"none"} and info_b["_reaction_params"].all()
        return obs_s

    obs = reset(0)
    for t in range(steps):
        if reset_every and t and t % reset_every == 0:
            obs = reset(t // reset_every)
        actions = (
            rng.uniform(-1, 1, (num_envs, 2)).astype(np.float32)
            if policy is None
            else np.stack([policy(i, {k: v[i] for k, v in obs.items()}, rng) for i in range(num_envs)])
        )
        out_s = sync.step(actions)
        out_b = batched.step(actions)
        for key in out_s[0]:
            np.testing.assert_array_equal(out_b[0][key], out_s[0][key], err_msg=f"step {t} obs {key}")
        for i, name in ((1, "reward"), (2, "terminated"), (3, "truncated")):
            assert out_b[i].dtype == out_s[i].dtype, name
            np.testing.assert_array_equal(out_b[i], out_s[i], err_msg=f"step {t} {name}")
        assert_same_info(out_s[4], out_b[4], f"step {t} info")
        obs = out_s[0]
        counts["steps"] += 1
        ended_itself = out_s[4].get("_episode_metrics", np.zeros(num_envs, dtype=bool))
        counts["limited"] += int(np.sum(out_s[3] & ~ended_itself))
        if "forecasts" in obs:
            counts["forecast_rows"] += int(obs["mask"].sum())
        if "episode_metrics" in out_s[4]:
            for i in np.flatnonzero(out_s[4]["_episode_metrics"]).tolist():
                m = out_s[4]["episode_metrics"]
                counts["ended"] += 1
                counts["collisions"] += int(m["outcome"][i] == "collision")
                counts["popin_events"] += int(m["popin_events"][i])
                ttc = m["min_ttc_s"][i]  # None, or NaN in a float column whose first world had a float
                counts["ttc_finite"] += ttc is not None and bool(np.isfinite(ttc))
                counts["accel"] += bool(m["mean_accel_mps2"][i] > 0)
                counts["spl"] += bool(m["spl"][i])
                assert {key: m[key][i] for key in UNDISTURBED} == UNDISTURBED
    sync.close()
    batched.close()
    return counts


@pytest.fixture
def side_by_side() -> Callable[..., dict[str, int]]:
    return run_side_by_side
