"""Where the crowd comes from: a named ETH/UCY scene needs the data (an error naming where the project looked,
never a silent substitute); the synthetic crowd is there when asked for, and as the embedded default of a bare
``gymnasium.make(id)``, which says so; every environment names its crowd source."""

from __future__ import annotations

import warnings
from pathlib import Path

import gymnasium as gym
import pytest

import crowdnav_mesrnn  # noqa: F401  (registers the ids)
from crowdnav_mesrnn.data import ENV_VAR, DataNotFoundError
from envs.config import crowd_source
from envs.crowd_nav import CrowdNavEnv


@pytest.fixture
def empty_data(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``$CROWDNAV_MESRNN_DATA`` points at an empty folder (a user who has not downloaded the data yet)."""
    folder = tmp_path / "eth_ucy"
    folder.mkdir()
    monkeypatch.setenv(ENV_VAR, str(folder))
    return folder


@pytest.mark.parametrize(
    "kwargs",
    [
        {"split": "zara1", "part": "test"},
        {"split": "zara1"},
        {"part": "train"},
        {"scenes": ["univ"], "split": "zara1"},
        {"config": {"split": "hotel"}},
    ],
)
def test_a_named_scene_without_data_is_an_error_naming_where_it_looked(kwargs: dict, empty_data: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not a warning and a substitute: an error
        with pytest.raises(DataNotFoundError) as info:
            gym.make("CrowdNav-MESRNN-v0", **kwargs)
    msg = str(info.value)
    assert str(empty_data) in msg and ENV_VAR in msg and "crowd='synthetic'" in msg


def test_a_config_file_naming_a_split_needs_the_data(empty_data: Path, tmp_path: Path) -> None:
    path = tmp_path / "env.yaml"
    path.write_text("split: univ\n")
    with pytest.raises(DataNotFoundError, match="univ"):
        CrowdNavEnv(config=str(path), predictor="none")


def test_a_bare_make_keeps_the_embedded_synthetic_default_and_says_so(empty_data: Path) -> None:
    with pytest.warns(UserWarning, match=r"no scene named.*synthetic"):
        env = gym.make("CrowdNav-NoPred-v0")
    _, info = env.reset(seed=0)
    assert env.unwrapped.crowd_kind == "synthetic" and info["crowd"] == "synthetic"
    assert "synthetic" in env.unwrapped.crowd_source.describe()
    env.close()


def test_the_synthetic_crowd_asked_for_needs_no_data_and_no_warning(empty_data: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make("CrowdNav-NoPred-v0", split="zara1", part="test", crowd="synthetic")
    assert env.unwrapped.crowd_source.kind == "synthetic" and env.unwrapped.crowd_source.data_dir is None


def test_a_replayed_crowd_names_its_data_folder(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="none", split="zara1", part="test")
    source = env.crowd_source
    assert source.kind == "replay" and source.data_dir == str(data_dir)
    assert str(data_dir) in source.describe()
    assert crowd_source(env.config, scene_named=True) == source
    assert source.as_dict() == {"kind": "replay", "data_dir": str(data_dir)}
