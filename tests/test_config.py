"""``crowdnav_mesrnn.config``: an unknown key leads with the closest valid one, wherever configs are checked."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from crowdnav_mesrnn.config import ConfigError, UnknownKeyError, check_keys, close_matches

REPO = Path(__file__).resolve().parent.parent


def test_close_matches_suggests_the_nearest_valid_key() -> None:
    valid = ("num_pedestrians", "sensor_range_m", "horizon_steps")
    assert close_matches("num_pedestrian", valid) == ["num_pedestrians"]
    assert close_matches("zzz", valid) == []


def test_check_keys_leads_with_the_suggestion_and_keeps_the_valid_list() -> None:
    with pytest.raises(ConfigError) as info:
        check_keys({"num_pedestrian": 3}, ["num_pedestrians", "sensor_range_m"], "env config")
    msg = str(info.value)
    assert msg.startswith("unknown env config key 'num_pedestrian'; did you mean 'num_pedestrians'?")
    assert msg.endswith("(valid keys: num_pedestrians, sensor_range_m)")
    with pytest.raises(ConfigError) as info:
        check_keys({"qqq": 1}, ["num_pedestrians"], "env config")
    assert "did you mean" not in str(info.value) and "valid keys: num_pedestrians" in str(info.value)


def _env_make() -> None:
    import gymnasium as gym

    import crowdnav_mesrnn  # noqa: F401 (registers the ids)

    gym.make("CrowdNav-CV-v0", crowd="empty", num_pedestrian=3)


def _env_yaml(tmp_path: Path) -> None:
    from envs.crowd_nav import CrowdNavEnv

    path = tmp_path / "env.yaml"
    path.write_text("sensor_rang_m: 5.0\n")
    CrowdNavEnv(config=str(path), crowd="empty", predictor="none")


def _reset_option() -> None:
    from envs.crowd_nav import CrowdNavEnv

    CrowdNavEnv(crowd="empty", predictor="none").reset(seed=0, options={"t0": 1.0})


def _train(key: str) -> Callable[[], Any]:
    def load() -> Any:
        from agents.training.config import load_train_config

        return load_train_config(REPO / "configs" / "agent" / "ppo.yaml", None, {key: 1, "env.crowd": "synthetic"})

    return load


def _predictor_train() -> None:
    from crowdnav_mesrnn.training.trainer import load_configs

    load_configs("srnn", overrides={"bach_size": 3})


def _predictor_model() -> None:
    from crowdnav_mesrnn.models.architecture import ModelConfig

    ModelConfig.from_dict({"model": "srnn", "node_hiden": 8})


def _action() -> None:
    from agents.actions import make_actions
    from envs.config import CrowdNavConfig

    make_actions(CrowdNavConfig(), {"heading_deg": [0, 30]})


@pytest.mark.parametrize(
    ("load", "wrong", "right"),
    [
        (_env_make, "num_pedestrian", "num_pedestrians"),
        ("env_yaml", "sensor_rang_m", "sensor_range_m"),
        (_reset_option, "t0", "t0_s"),
        (_train("learning_rat"), "learning_rat", "learning_rate"),
        (_train("eval.episode"), "episode", "episodes"),
        (_train("pretrain.episode"), "episode", "episodes"),
        (_train("env.num_pedestrian"), "num_pedestrian", "num_pedestrians"),
        (_predictor_train, "bach_size", "batch_size"),
        (_predictor_model, "node_hiden", "node_hidden"),
        (_action, "heading_deg", "headings_deg"),
    ],
)
def test_every_config_suggests_the_closest_key(load: Any, wrong: str, right: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=rf"'{wrong}'; did you mean '{right}'\?.*valid keys: .*{right}"):
        _env_yaml(tmp_path) if load == "env_yaml" else load()


def test_several_unknown_keys_each_get_their_suggestion() -> None:
    with pytest.raises(ConfigError) as info:
        check_keys({"num_pedestrian": 1, "qqq": 2}, ["num_pedestrians"], "env config")
    assert str(info.value) == (
        "unknown env config keys 'num_pedestrian' (did you mean 'num_pedestrians'?), 'qqq' (valid keys: num_pedestrians)"
    )


def test_an_unknown_keyword_of_the_environment_is_a_type_error_naming_it() -> None:
    """Libraries probing a constructor (TorchRL's GymEnv passes frameskip=) take only a TypeError as "not
    supported"; the project's callers still catch it as a ConfigError (a ValueError)."""
    import gymnasium as gym

    import crowdnav_mesrnn  # noqa: F401 (registers the ids)

    with pytest.raises(TypeError) as info:
        gym.make("CrowdNav-MESRNN-v0", frameskip=4)
    assert isinstance(info.value, UnknownKeyError) and isinstance(info.value, ConfigError)
    assert isinstance(info.value, ValueError)
    assert "unknown env config key 'frameskip'" in str(info.value)
    assert "unexpected keyword argument 'frameskip'" in str(info.value)  # Python's wording, which peers look for
    with pytest.raises(TypeError, match=r"'num_pedestrian'; did you mean 'num_pedestrians'\?"):
        gym.make("CrowdNav-CV-v0", crowd="empty", num_pedestrian=3)


@pytest.mark.parametrize("kwargs", [{"dt_s": -0.4}, {"split": "paris"}, {"terminate_on_collision": "no"}])
def test_a_bad_value_of_a_known_key_stays_a_value_error(kwargs: dict[str, Any]) -> None:
    import gymnasium as gym

    import crowdnav_mesrnn  # noqa: F401 (registers the ids)

    with pytest.raises(ConfigError) as info:
        gym.make("CrowdNav-CV-v0", crowd="empty", **kwargs)
    assert not isinstance(info.value, TypeError)


def test_an_unknown_key_of_a_config_file_is_not_called_a_keyword_argument(tmp_path: Path) -> None:
    with pytest.raises(UnknownKeyError) as info:
        _env_yaml(tmp_path)
    assert isinstance(info.value, TypeError) and info.value.keys == ("sensor_rang_m",)
    assert "keyword argument" not in str(info.value)
