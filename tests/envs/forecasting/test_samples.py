"""``forecast_samples``: sampled futures of the observed pedestrians from the forecast source's distribution, drawn
by its head coherently with a seed fixed by the recording and the time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from crowdnav_mesrnn.config import ConfigError
from crowdnav_mesrnn.predictors import load
from envs.crowd_nav import CrowdNavEnv
from envs.observation import structured


def episode(
    predictor: str, steps: int, seed: int = 1, split: str = "zara1", **kw: object
) -> list[dict[str, np.ndarray]]:
    env = CrowdNavEnv(predictor=predictor, split=split, part="test", forecast_samples=20, **kw)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(np.array([0.3, 0.0], np.float32))
        out.append(obs)
        if terminated or truncated:
            break
    return out


def test_samples_have_their_shape_are_finite_and_zero_on_empty_rows(data_dir: Path) -> None:
    env = CrowdNavEnv(predictor="mesrnn", split="zara1", part="test", forecast_samples=20)
    assert env.observation_space["forecast_samples"].shape == (10 * 20 * 12 * 2,)
    seen = 0
    for obs in episode("mesrnn", 10):
        assert env.observation_space.contains(obs)
        o = structured(obs, 10, 12)
        smp, mask = o["forecast_samples"], obs["mask"].astype(bool)
        assert smp.shape == (10, 20, 12, 2) and np.all(np.isfinite(smp)) and np.all(smp[~mask] == 0)
        assert np.all(smp[mask].std(axis=1) > 0)  # spread at every step of every observed pedestrian
        seen += int(mask.sum())
    assert seen > 0


def test_cv_gaussian_samples_are_its_gaussian_drawn_coherently(data_dir: Path) -> None:
    """On a 0.4 s recording the env grid is the annotation grid: each sample is the forecast (the distribution's mean)
    plus the same standard normal draw times each step's scale a + b h."""
    sigma = load("cv_gaussian", "zara1").sigma_m()  # type: ignore[attr-defined]
    draws = []
    for obs in episode("cv_gaussian", 6, flatten_observation=False):
        mask = obs["mask"].astype(bool)
        z = (obs["forecast_samples"][mask] - obs["forecasts"][mask][:, None]) / sigma[None, None, :, None]  # (m,S,H,2)
        np.testing.assert_allclose(z, np.broadcast_to(z[:, :, :1], z.shape), atol=2e-4)
        draws.append(z[:, :, 0].reshape(-1))
    z = np.concatenate(draws)
    assert len(z) > 400 and abs(z.mean()) < 0.15 and abs(z.std() - 1.0) < 0.1


def test_samples_are_reproducible_and_fixed_by_recording_and_time(data_dir: Path) -> None:
    a = episode("cv_gaussian", 8, seed=2)
    b = episode("cv_gaussian", 8, seed=2)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x["forecast_samples"], y["forecast_samples"])
    assert not np.array_equal(a[3]["forecast_samples"], a[4]["forecast_samples"])  # a new draw at every step


def test_samples_on_the_0667_s_recording_start_from_the_annotated_position(data_dir: Path) -> None:
    """ETH (0.667 s annotations) resamples the draws onto 0.4 s steps: finite, and with every step moving away from the
    annotated position as the forecasts do."""
    for obs in episode("cv_gaussian", 8, split="eth", flatten_observation=False):
        mask = obs["mask"].astype(bool)
        smp = obs["forecast_samples"][mask]
        assert np.all(np.isfinite(smp))
        np.testing.assert_allclose(smp.mean(axis=1), obs["forecasts"][mask], atol=0.5)


@pytest.mark.parametrize("predictor", ["cv", "oracle", "none"])
def test_sources_without_a_distribution_are_refused(predictor: str) -> None:
    with pytest.raises(ConfigError, match=r"forecast_samples.*cv_gaussian, mesrnn, srnn, vlstm"):
        CrowdNavEnv(predictor=predictor, crowd="empty", forecast_samples=5)


def test_a_bad_count_is_refused_naming_the_key() -> None:
    with pytest.raises(ConfigError, match="'forecast_samples' must be an integer in \\[0, 1000\\], got -1"):
        CrowdNavEnv(predictor="cv_gaussian", crowd="empty", forecast_samples=-1)
