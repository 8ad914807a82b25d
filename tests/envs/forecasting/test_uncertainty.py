"""The optional ``forecast_uncertainty`` observation key: same shape in every arm with forecasts, radii that
mean what they say (exact for the noisy oracle, calibrated for constant velocity), calibrations cached."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from envs.crowd_nav import CrowdNavEnv
from envs.forecasting.sources import NoisyOracleForecast
from envs.forecasting.uncertainty import CalibratedUncertainty, NoisyOracleUncertainty


def first_obs(predictor: str, steps: int = 3, **kw: Any) -> tuple[CrowdNavEnv, dict[str, np.ndarray]]:
    env = CrowdNavEnv(predictor=predictor, split="zara1", part="test", **kw)
    obs, _ = env.reset(seed=1)
    for _ in range(steps):
        obs, *_ = env.step(np.zeros(2, np.float32))
    return env, obs


def test_the_key_is_optional_and_has_one_shape_in_every_arm(data_dir: Path) -> None:
    _, plain = first_obs("cv")
    assert "forecast_uncertainty" not in plain
    shapes = {}
    for arm in ("cv", "oracle", "noisy_oracle"):
        env, obs = first_obs(arm, forecast_uncertainty=True)
        assert env.observation_space.contains(obs)
        unc = obs["forecast_uncertainty"]
        shapes[arm] = unc.shape
        mask = obs["mask"].astype(bool)
        assert mask.any()
        radii = unc.reshape(10, 12)
        assert np.all(radii[~mask] == 0)
        if arm == "oracle":
            assert np.all(radii == 0)
        else:  # grows with the horizon
            assert np.all(np.diff(radii[mask], axis=1) >= 0) and np.all(radii[mask][:, -1] > 0.5)
    assert set(shapes.values()) == {(120,)}
    env, obs = first_obs("cv", forecast_uncertainty=True, flatten_observation=False)
    assert obs["forecast_uncertainty"].shape == (10, 12)
    _, none = first_obs("none", forecast_uncertainty=True)
    assert "forecast_uncertainty" not in none and "forecasts" not in none


def test_noisy_oracle_radius_holds_its_noise_at_the_level() -> None:
    source = NoisyOracleForecast(0.5, 12)
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, source.sigma, size=(40_000, 1, 2))
    err = np.linalg.norm(source.ramp * z, axis=-1)  # (n, H)
    for level in (0.5, 0.9):
        radius = NoisyOracleUncertainty(source, level).per_step
        assert np.mean(err <= radius[None, :]) == pytest.approx(level, abs=0.01)


def test_calibrations_are_cached_on_disk_and_reused(
    data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import crowdnav_mesrnn.uncertainty.calibration as calibration

    src = CalibratedUncertainty("cv", "zara1", 0.9, 0.4, 12, tmp_path, str(data_dir))
    cal = src.calibration("zara1")
    assert list((tmp_path / "calibration").glob("cv_zara1_*.json"))
    slow, fast = cal.radius_m(0.9, np.array([0.0, 0.6]))
    assert np.all(fast > slow) and np.all(np.diff(slow) > 0)
    assert set(cal.thresholds) == {"0.5", "0.9", "0.95"}

    def refuse(*args: Any, **kw: Any) -> None:
        raise AssertionError("fitted again instead of reading the cache")

    monkeypatch.setattr(calibration, "fit_calibration", refuse)
    again = CalibratedUncertainty("cv", "zara1", 0.9, 0.4, 12, tmp_path, str(data_dir)).calibration("zara1")
    assert again == cal


def test_sources_without_a_calibration_are_errors(data_dir: Path, fake_predictor: Any) -> None:
    with pytest.raises(ConfigError, match="needs a named forecast source"):
        CrowdNavEnv(predictor=fake_predictor(), split="zara1", part="test", forecast_uncertainty=True)
    with pytest.raises(ConfigError, match="forecast_uncertainty_level"):
        CrowdNavEnv(predictor="cv", forecast_uncertainty=True, forecast_uncertainty_level=1.0)
