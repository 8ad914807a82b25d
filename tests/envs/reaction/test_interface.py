"""The interface the environment calls: parameters (validation, spec), the factory, per-substep and per-control-step
stepping (the same), determinism, and clear errors on misuse."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from envs.reaction import REACTION_MODELS, ReactionParams, make_reactive_crowd
from envs.replay import Replay


def test_params_defaults_spec_and_round_trip() -> None:
    params = ReactionParams()
    spec = params.to_dict()
    assert list(spec) == [f.name for f in dataclasses.fields(ReactionParams)]
    assert all(isinstance(v, int | float) and not isinstance(v, bool) for v in spec.values())
    assert ReactionParams.from_mapping(spec) == params
    assert ReactionParams.from_mapping({"trigger_distance_m": 4, "release_distance_m": 5}).trigger_distance_m == 4.0


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        ({"trigger_distance_m": -1.0}, ["'trigger_distance_m'", "-1.0", "> 0"]),
        ({"max_speed_mps": float("nan")}, ["'max_speed_mps'", "nan", "finite"]),
        ({"orca_max_neighbors": 2.5}, ["'orca_max_neighbors'", "2.5", "integer"]),
        ({"orca_max_neighbors": True}, ["'orca_max_neighbors'", "True", "integer"]),
        ({"sf_anisotropy": 1.5}, ["'sf_anisotropy'", "1.5", "[0, 1]"]),
        ({"release_distance_m": 2.0}, ["'release_distance_m'", "2.0", "'trigger_distance_m'", "3.0"]),
        ({"trigger_distanse_m": 3.0}, ["'trigger_distanse_m'", "did you mean 'trigger_distance_m'", "valid keys"]),
    ],
)
def test_bad_params_name_the_key_the_value_and_what_is_allowed(overrides: dict, words: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        ReactionParams.from_mapping(overrides)
    for word in words:
        assert word in str(err.value)


def test_the_docs_page_names_every_parameter_with_its_source() -> None:
    """``docs/reaction.md``'s parameter table has a row for every field (its values come from the code)."""
    page = (Path(__file__).resolve().parents[3] / "docs" / "reaction.md").read_text(encoding="utf-8")
    rows = {line.split("|")[1].strip().strip("`") for line in page.splitlines() if line.startswith("| `")}
    assert {f.name for f in dataclasses.fields(ReactionParams)} <= rows


def test_an_unknown_model_lists_the_valid_ones() -> None:
    with pytest.raises(ConfigError, match="unknown reaction 'rvo'; valid: none, pause, orca, social_force"):
        make_reactive_crowd("rvo", robot_radius_m=0.3, pedestrian_radius_m=0.3)


@pytest.mark.parametrize("model", REACTION_MODELS)
def test_advance_is_the_substeps_one_by_one_and_runs_repeat(kit, model: str) -> None:
    """One call per control step (4 substeps) equals four calls per substep at the same times, bit for bit; and a
    second run of the same episode is the same (no randomness)."""
    rec = kit.head_on_recording(num=10)
    robot = kit.moving_robot((6.0, 0.0), (-1.0, 0.0))
    first = kit.simulate(model, rec, robot, seconds=12.0)
    again = kit.simulate(model, rec, robot, seconds=12.0)
    assert np.array_equal(first.present, again.present)
    assert np.array_equal(first.positions[first.present], again.positions[again.present])
    assert first.reacted.any() or model == "none"
    replay = Replay(rec)
    by_call, by_step = (make_reactive_crowd(model, robot_radius_m=0.3, pedestrian_radius_m=0.3) for _ in range(2))
    by_call.reset(replay, 0.0)
    by_step.reset(replay, 0.0)
    dt = kit.dt_s
    for c in range(30):
        t = c * 4 * dt
        times = t + dt * np.arange(5)
        rec_pos, rec_present = replay.positions_at(times)
        path = np.array([robot(x)[0] for x in times])
        seen = np.array([robot(x)[1] for x in times[:4]])
        got = by_call.advance(t, dt, rec_pos, rec_present, path, seen)
        for k in range(4):
            out = by_step.step(
                times[k], dt, rec_pos[k], rec_present[k], rec_pos[k + 1], rec_present[k + 1], path[k], seen[k]
            )
            assert np.array_equal(got.present[k + 1], out.present)
            assert np.array_equal(got.positions[k + 1][out.present], out.positions[out.present])


def test_misuse_is_a_clear_error(kit) -> None:
    rec = kit.head_on_recording(num=3)
    replay = Replay(rec)
    crowd = make_reactive_crowd("orca", robot_radius_m=0.3, pedestrian_radius_m=0.3)
    n = replay.num_pedestrians
    args = (
        np.zeros((n, 2)),
        np.ones(n, dtype=bool),
        np.zeros((n, 2)),
        np.ones(n, dtype=bool),
        np.zeros(2),
        np.zeros(2),
    )
    with pytest.raises(RuntimeError, match="reset"):
        crowd.step(0.0, 0.1, *args)
    crowd.reset(replay, 0.0)
    with pytest.raises(ValueError, match=r"t_s = 0\.5 s, but the crowd is at 0\.0 s"):
        crowd.step(0.5, 0.1, *args)
    with pytest.raises(ValueError, match="dt_s must be > 0"):
        crowd.step(0.0, 0.0, *args)
    with pytest.raises(ValueError, match=r"recorded_next must have shape \(3, 2\), got \(2, 2\)"):
        crowd.step(0.0, 0.1, args[0], args[1], np.zeros((2, 2)), *args[3:])
