"""Evaluation of distributions (NLL, best-of-K) and conformal calibration: known answers on synthetic
forecasts, the error model's fit, and the commands' JSON on real windows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdnav_mesrnn.cli import main
from crowdnav_mesrnn.data import MinMax
from crowdnav_mesrnn.data.windows import Window
from crowdnav_mesrnn.evaluation.metrics import ScoredForecasts, collect_forecasts
from crowdnav_mesrnn.evaluation.protocol import evaluate_model
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.architecture import ModelConfig
from crowdnav_mesrnn.models.learned import LearnedPredictor, lean_state
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN
from crowdnav_mesrnn.uncertainty.calibration import fit_calibration, forecaster_for
from crowdnav_mesrnn.uncertainty.conformal import (
    Calibration,
    ErrorModel,
    conformal_quantile,
    measure_coverage,
    region_scores,
)


def synthetic_scored(m: int, seed: int, a: float = 0.1, b: float = 0.8, windows: int = 0) -> ScoredForecasts:
    """Errors drawn from isotropic Gaussians with scale ``(a + b v) (h + 1) / 12``."""
    rng = np.random.default_rng(seed)
    speed = rng.uniform(0.0, 0.8, m)
    ramp = np.arange(1, 13) / 12
    sigma = (a + b * speed)[:, None] * ramp[None, :]
    error = rng.normal(size=(m, 12, 2)) * sigma[..., None]
    w = windows or m
    return ScoredForecasts(error, speed, np.sort(rng.integers(0, w, m)), w)


def test_conformal_quantile_is_the_finite_sample_rank() -> None:
    scores = np.arange(1.0, 10.0)  # n = 9
    assert conformal_quantile(scores, 0.9) == 9.0  # ceil(10 * 0.9) = 9th smallest
    assert conformal_quantile(scores, 0.5) == 5.0  # ceil(5) = 5th
    assert conformal_quantile(scores[:8], 0.9) == np.inf  # ceil(8.1) = 9 > 8
    with pytest.raises(ValueError, match="coverage level"):
        conformal_quantile(scores, 0.0)


def test_error_model_recovers_the_scale_and_conformal_regions_cover_exchangeable_data() -> None:
    cal_set = synthetic_scored(20_000, seed=0)
    em = ErrorModel.fit(cal_set)
    ramp = np.arange(1, 13) / 12
    np.testing.assert_allclose(em.a_m, 0.1 * ramp, rtol=0.1, atol=0.004)
    np.testing.assert_allclose(em.b, 0.8 * ramp, rtol=0.05)
    # The error model is the truth here: its raw regions and the calibrated ones both cover at their level
    scores = region_scores(cal_set, "scaled", em)
    thresholds = {f"{c:g}": tuple(conformal_quantile(scores[:, h], c) for h in range(12)) for c in (0.5, 0.9)}
    cal = Calibration("cv", "point", "zara1", "scaled", thresholds, em, 1, len(cal_set.speed))
    test = synthetic_scored(20_000, seed=1, windows=500)
    cov = measure_coverage(cal, test, (0.5, 0.9))
    for key, level in (("0.5", 0.5), ("0.9", 0.9)):
        assert cov.pooled(key).estimate == pytest.approx(level, abs=0.01)
        assert cov.pooled(key, raw=True).estimate == pytest.approx(level, abs=0.01)
    # The disc of radius_m holds the region: every covered error lies inside it
    r = cal.radius_m(0.9, test.speed)
    inside = np.linalg.norm(test.error, axis=-1) <= r
    assert np.all(inside[scores_of(cal, test) <= cal.threshold(0.9)[None, :]])


def scores_of(cal: Calibration, scored: ScoredForecasts) -> np.ndarray:
    return region_scores(scored, cal.score, cal.error_model)


def test_a_shifted_scene_is_not_covered_and_says_so() -> None:
    """Calibrated on slow errors, measured on errors twice as large: coverage falls well below the level."""
    cal_set = synthetic_scored(5000, seed=0)
    em = ErrorModel.fit(cal_set)
    scores = region_scores(cal_set, "radius")
    cal = Calibration("cv", "point", "zara1", "radius", {"0.9": tuple(np.quantile(scores, 0.9, axis=0))}, None, 1, 1)
    shifted = synthetic_scored(5000, seed=1, a=0.2, b=1.6)
    assert measure_coverage(cal, shifted, (0.9,)).pooled("0.9").estimate < 0.6
    assert em.sigma(np.zeros(1)).min() >= 0.01  # the floor


def fake_windows(n_windows: int, rng: np.random.Generator) -> list[Window]:
    out = []
    for _ in range(n_windows):
        n = 3
        pos = np.cumsum(rng.normal(0.3, 0.1, (20, n, 2)), 0).astype(np.float32)
        pres = np.ones((20, n), bool)
        out.append(Window(pos, pres, pres.all(0), "fake", 0, np.arange(n)))
    return out


def test_best_of_k_and_nll_known_answers() -> None:
    rng = np.random.default_rng(0)
    windows = fake_windows(5, rng)

    def truth_sampler(pos: torch.Tensor, mask: torch.Tensor, k: int) -> torch.Tensor:
        future = pos[:, 8:]  # one sample is the truth, the others far away
        far = future[:, None].repeat(1, k, 1, 1, 1) + 5.0
        far[:, 1] = future
        return far

    def unit_gaussian(pos: torch.Tensor, mask: torch.Tensor) -> gaussian.GaussianForecast:
        mean = pos[:, 8:] + torch.tensor([0.3, -0.4])
        return gaussian.GaussianForecast(mean, torch.ones_like(mean), torch.zeros(mean.shape[:-1]))

    got = collect_forecasts(windows, distribution=unit_gaussian, sample=truth_sampler, samples=3)
    assert np.all(got.min_ade == 0) and np.all(got.min_fde == 0)
    assert got.error.shape == (15, 12, 2) and np.all(got.window == np.repeat(np.arange(5), 3))
    np.testing.assert_allclose(got.error, np.broadcast_to([0.3, -0.4], got.error.shape), atol=1e-6)
    nll = gaussian.nll(got.error, got.sigma, got.rho)
    np.testing.assert_allclose(nll, np.log(2 * np.pi) + 0.5 * 0.25, rtol=1e-6)


def tiny_gaussian_checkpoint(path: Path, split: str, model: str = "vlstm") -> Path:
    torch.manual_seed(0)
    net = StructuralRNN(
        ModelConfig(model=model, head="gaussian", node_embed=8, node_hidden=16, edge_embed=4, edge_hidden=8)
    )
    norm = MinMax((-5.0, -5.0), (20.0, 20.0))
    torch.save(
        {
            "model_config": net.cfg.to_dict(),
            "state_dict": lean_state(net),
            "norm": norm.to_dict(),
            "train_config": {"split": split},
        },
        path,
    )
    return path


def test_eval_with_samples_adds_best_of_k_with_intervals(data_dir: Path, tmp_path: Path) -> None:
    for split in ("eth", "hotel"):
        tiny_gaussian_checkpoint(tmp_path / f"g_{split}.pt", split)
    from crowdnav_mesrnn.models.learned import load_predictor

    res = evaluate_model(
        "vlstm",
        ["eth", "hotel"],
        data_dir=data_dir,
        checkpoint_for=lambda s: load_predictor(tmp_path / f"g_{s}.pt", split=s),
        samples=5,
        n_resamples=200,
    )
    for key in ("eth", "hotel", "average"):
        row = res["splits"][key]
        for metric in ("nll_m", "min_ade_m", "min_fde_m"):
            lo, hi = row[f"{metric}_ci"]
            assert lo <= row[metric] <= hi
        assert row["min_ade_m"] < row["ade_m"] + 1.0
    avg = res["splits"]["average"]
    assert avg["min_ade_m"] == pytest.approx(np.mean([res["splits"][s]["min_ade_m"] for s in ("eth", "hotel")]))
    # more samples, closer best sample (same seed streams, K = 1 vs 5)
    one = evaluate_model(
        "vlstm",
        ["eth"],
        data_dir=data_dir,
        checkpoint_for=lambda s: load_predictor(tmp_path / f"g_{s}.pt", split=s),
        samples=1,
        n_resamples=50,
    )
    assert res["splits"]["eth"]["min_ade_m"] < one["splits"]["eth"]["min_ade_m"]


def test_eval_samples_need_a_distribution(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="point head"):
        evaluate_model("vlstm", "eth", data_dir=data_dir, samples=2, head="point")
    with pytest.raises(ValueError, match="'cv' forecasts one point"):
        evaluate_model("cv", "eth", data_dir=data_dir, samples=2)


def test_calibrate_cli_json_for_constant_velocity(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["predictor", "calibrate", "--model", "cv", "--split", "zara1", "--json", "--resamples", "200"]) == 0
    res = json.loads(capsys.readouterr().out)
    row = res["splits"]["zara1"]
    assert set(row["coverage"]) == {"0.5", "0.9", "0.95"}
    assert row["coverage"]["0.5"] < row["coverage"]["0.9"] < row["coverage"]["0.95"]
    for key, value in row["coverage"].items():
        assert row["coverage_ci"][key][0] <= value <= row["coverage_ci"][key][1]
        assert len(row["coverage_per_step"][key]) == 12
        assert np.mean(row["coverage_per_step"][key]) == pytest.approx(value)
    assert set(row["raw_coverage"]) == {"0.5", "0.9", "0.95"} and row["calibration_windows"] > 0
    # thresholds grow with the level; the error model's scale grows with the horizon
    assert all(a < b for a, b in zip(row["thresholds"]["0.5"], row["thresholds"]["0.9"], strict=True))
    assert row["error_model"]["a_m"][-1] > row["error_model"]["a_m"][0]


def test_calibration_with_a_distribution_uses_its_gaussians(data_dir: Path, tmp_path: Path) -> None:
    from crowdnav_mesrnn.models.learned import load_predictor

    pred = load_predictor(tiny_gaussian_checkpoint(tmp_path / "g.pt", "eth"), split="eth")
    assert isinstance(pred, LearnedPredictor)
    fc = forecaster_for("vlstm", "eth", predictor=pred)
    cal = fit_calibration(fc, "eth", data_dir=data_dir)
    assert cal.head == "gaussian" and cal.error_model is None
    val_coverage = measure_coverage(cal, fc.collect(split_windows_val(data_dir)))
    assert val_coverage.pooled("0.9").estimate == pytest.approx(0.9, abs=0.02)  # conformal on its own data


def split_windows_val(data_dir: Path) -> list[Window]:
    from crowdnav_mesrnn.data.windows import split_windows

    return split_windows("eth", "val", 2, data_dir)
