"""The scores of sampled futures (``predictor evaluate --samples``): the energy score against a brute-force
computation and as a proper scoring rule, Social-GAN's per-scene best-of-K against the per-pedestrian one, the
sampling schemes, and the paired interval of ``--versus``, all on tiny synthetic data."""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import pytest
import torch

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN
from crowdnav_mesrnn.data.windows import Window
from crowdnav_mesrnn.evaluation import protocol
from crowdnav_mesrnn.evaluation.metrics import batches, collect_forecasts, energy_score
from crowdnav_mesrnn.evaluation.statistics import PairedErrors, block_bootstrap_ci
from crowdnav_mesrnn.models.cv_gaussian import CvGaussian, CvGaussianParams

T = OBS_LEN + PRED_LEN


def brute_energy(x: np.ndarray, y: np.ndarray) -> float:
    """``(K, D)`` samples, ``(D,)`` truth: the energy score's unbiased estimate, by loops."""
    k = len(x)
    to_truth = sum(math.sqrt(sum((a - b) ** 2 for a, b in zip(xi, y, strict=True))) for xi in x) / k
    pairs = [
        math.sqrt(sum((a - b) ** 2 for a, b in zip(x[i], x[j], strict=True)))
        for i, j in itertools.permutations(range(k), 2)
    ]
    return to_truth - 0.5 * sum(pairs) / (k * (k - 1))


def test_energy_score_equals_a_brute_force_computation() -> None:
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(3, 5, 24)), rng.normal(size=(3, 24))
    got = energy_score(torch.from_numpy(x), torch.from_numpy(y)).numpy()
    assert got == pytest.approx([brute_energy(x[i], y[i]) for i in range(3)], rel=1e-12)
    # One dimension: E|X − y| − ½ E|X − X'|, with two samples by hand.
    two = energy_score(torch.tensor([[[0.0], [2.0]]]), torch.tensor([[1.0]]))
    assert two.item() == pytest.approx((1 + 1) / 2 - 0.5 * 2.0)
    with pytest.raises(ValueError, match="at least 2 samples"):
        energy_score(torch.zeros(1, 1, 24), torch.zeros(1, 24))


def test_the_true_distribution_minimises_the_expected_energy_score() -> None:
    """Truths drawn from N(0, I) in 24 dimensions; forecasts N(m, s² I). The mean score over many truths is lowest
    for the true distribution, against too narrow, too wide, shifted and step-coherent (rank-one) forecasts."""
    gen = torch.Generator().manual_seed(0)
    m, k, d = 4000, 20, 24
    y = torch.randn((m, d), generator=gen, dtype=torch.float64)

    def mean_score(scale: float, shift: float = 0.0, coherent: bool = False) -> float:
        eps = torch.randn((m, k, 1 if coherent else d), generator=gen, dtype=torch.float64).expand(m, k, d)
        return energy_score(shift + scale * eps, y).mean().item()

    truth = mean_score(1.0)
    for other in (mean_score(0.8), mean_score(1.25), mean_score(1.0, shift=0.3), mean_score(1.0, coherent=True)):
        assert truth < other
    # The unbiased estimator is what makes this work at K = 20: the biased one (the V-statistic, k = l kept in the
    # second sum) under-counts the spread and prefers a narrower forecast (the same draws, scaled).
    eps = torch.randn((m, k, d), generator=gen, dtype=torch.float64)

    def both(scale: float) -> tuple[float, float]:
        x = scale * eps
        biased = (x - y[:, None]).norm(dim=-1).mean(1) - 0.5 * torch.cdist(x, x).mean((1, 2))
        return energy_score(x, y).mean().item(), biased.mean().item()

    (fair_true, biased_true), (fair_narrow, biased_narrow) = both(1.0), both(0.9)
    assert fair_true < fair_narrow and biased_narrow < biased_true


def window(rng: np.random.Generator, n: int, start: int, speed: float = 0.3) -> Window:
    """``n`` pedestrians walking straight with noise, all scored, plus one context pedestrian present only early."""
    steps = np.arange(T, dtype=np.float32)[:, None, None]
    heading = rng.uniform(-np.pi, np.pi, size=(1, n, 1))
    v = speed * np.concatenate([np.cos(heading), np.sin(heading)], axis=-1)
    pos = (rng.uniform(-5, 5, size=(1, n, 2)) + steps * v + rng.normal(0, 0.05, size=(T, n, 2))).astype(np.float32)
    pos = np.concatenate([pos, np.zeros((T, 1, 2), np.float32)], axis=1)
    present = np.ones((T, n + 1), bool)
    present[OBS_LEN - 3 :, n] = False
    pos[~present] = 0.0
    scored = present.all(0)
    return Window(pos, present, scored, "synthetic", start, np.arange(n + 1))


@pytest.fixture
def windows() -> list[Window]:
    rng = np.random.default_rng(1)
    return [window(rng, n, i) for i, n in enumerate([2, 3, 4, 2, 5, 3, 2, 4] * 5)]


def cvg(b: float) -> CvGaussian:
    return CvGaussian(CvGaussianParams(0.0, b, "b*h"))


def draw(model: CvGaussian, coherent: bool, seed: int = 0) -> Any:
    gen = torch.Generator().manual_seed(seed)
    return lambda pos, mask, k: model.sample_batch(pos, mask, k, gen, coherent=coherent)


def test_per_scene_best_of_k_is_the_brute_force_minimum_and_at_least_the_per_pedestrian_one(
    windows: list[Window],
) -> None:
    model, k = cvg(0.08), 6
    sampled: list[torch.Tensor] = []

    def keep(pos: torch.Tensor, mask: torch.Tensor, n: int) -> torch.Tensor:
        out = draw(model, coherent=False)(pos, mask, n)
        sampled.append(out)
        return out

    # Batches of one window, so each batch's samples are that window's.
    scored = collect_forecasts(
        windows, distribution=model.predict_distribution_batch, sample=keep, samples=k, batch_size=1
    )
    assert scored.scene_min_ade is not None and scored.scene_min_fde is not None and scored.min_ade is not None
    per_ped_sum = scored.window_sums(scored.min_ade)
    order = [chunk[0] for chunk in batches(windows, 1)]  # the windows in the order they were sampled
    for w, x in zip(order, sampled, strict=True):
        win = windows[w]
        truth = win.positions[OBS_LEN:][:, win.scored]  # (P, n, 2)
        x = x[0][:, :, win.scored].numpy()  # (K, P, n, 2)
        d = np.linalg.norm(x - truth[None], axis=-1)  # (K, P, n)
        assert scored.scene_min_ade[w] == pytest.approx(d.mean(1).sum(-1).min())
        assert scored.scene_min_fde[w] == pytest.approx(d[:, -1].sum(-1).min())
        assert per_ped_sum[w] == pytest.approx(d.mean(1).min(0).sum())
    assert np.all(scored.scene_min_ade >= per_ped_sum - 1e-12)
    assert np.all(scored.scene_min_fde >= scored.window_sums(scored.min_fde) - 1e-12)
    assert scored.scene_min_ade.sum() > per_ped_sum.sum()  # strictly, with several pedestrians per window
    # The energy score of each pedestrian is the brute-force one over its own 24 coordinates.
    first = order.index(0)
    x0 = sampled[first][0][:, :, windows[0].scored].numpy()
    y0 = windows[0].positions[OBS_LEN:][:, windows[0].scored]
    assert scored.energy is not None
    assert scored.energy[0] == pytest.approx(brute_energy(x0[:, :, 0].reshape(k, -1), y0[:, 0].reshape(-1)))


class Spy(CvGaussian):
    """A cv_gaussian that records how it was asked to sample."""

    def __init__(self, b: float) -> None:
        super().__init__(CvGaussianParams(0.0, b, "b*h"))
        self.asked: list[bool] = []

    def sample_batch(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        self.asked.append(kwargs["coherent"])
        return super().sample_batch(*args, **kwargs)


@pytest.fixture
def synthetic(monkeypatch: pytest.MonkeyPatch, windows: list[Window]) -> dict[str, Spy]:
    """``evaluate_model`` on the synthetic windows (test and validation alike), with two hand-set cv_gaussians:
    ``cv_gaussian`` (b = 0.05) and a narrower one standing in for a head (registered as ``mesrnn``)."""
    from crowdnav_mesrnn.data.normalization import MinMax
    from crowdnav_mesrnn.uncertainty import calibration

    models = {"cv_gaussian": Spy(0.05), "mesrnn": Spy(0.02)}

    def split_windows(split: str, part: str, min_scored: int = 2, data_dir: Any = None) -> list[Window]:
        return windows

    monkeypatch.setattr(protocol, "split_windows", split_windows)
    monkeypatch.setattr(calibration, "split_windows", split_windows)
    monkeypatch.setattr(protocol, "split_norm", lambda split, data_dir=None: MinMax(np.zeros(2), np.ones(2)))
    monkeypatch.setattr(protocol, "load_shipped", lambda model, split, head="point": models[model])
    return models


def test_sampling_schemes_differ_as_defined(synthetic: dict[str, Spy]) -> None:
    kwargs = {"samples": 20, "n_resamples": 50, "splits": "hotel"}
    coherent = protocol.evaluate_model("cv_gaussian", sampling="coherent", **kwargs)["splits"]["hotel"]
    marginal = protocol.evaluate_model("cv_gaussian", sampling="marginal", **kwargs)["splits"]["hotel"]
    assert synthetic["cv_gaussian"].asked == [True, False]
    # Each step's Gaussian is the same: the NLL and the calibrated coverage do not depend on the scheme.
    assert coherent["nll_m"] == marginal["nll_m"] and coherent["coverage_90"] == marginal["coverage_90"]
    # The trajectory's joint distribution differs: so do the energy score and best-of-K.
    assert coherent["energy_m"] != marginal["energy_m"] and coherent["min_ade_m"] != marginal["min_ade_m"]
    with pytest.raises(ValueError, match="unknown sampling"):
        protocol.evaluate_model("cv_gaussian", sampling="joint", **kwargs)


def test_versus_intervals_are_of_the_paired_per_window_differences(synthetic: dict[str, Spy]) -> None:
    kwargs = {"samples": 20, "n_resamples": 400, "splits": ["hotel"]}
    res = protocol.evaluate_versus("mesrnn", ["cv_gaussian"], **kwargs)
    diff = res["versus"]["cv_gaussian"]["difference"]["hotel"]
    mine, other = res["splits"]["hotel"], res["versus"]["cv_gaussian"]["result"]["splits"]["hotel"]
    keys = ("nll_m", "energy_m", "min_ade_m", "scene_min_ade_m", "scene_min_fde_m", "coverage_90")
    sums: dict[str, dict[str, dict[str, PairedErrors]]] = {}
    for name in ("mesrnn", "cv_gaussian"):
        ds: dict[str, dict[str, PairedErrors]] = {}
        protocol.evaluate_model(name, distribution_sums=ds, **kwargs)
        sums[name] = ds
    for key in keys:
        assert diff[key] == pytest.approx(mine[key] - other[key])
        a, b = sums["mesrnn"]["hotel"][key], sums["cv_gaussian"]["hotel"][key]
        paired = PairedErrors(a.diff_sum - b.diff_sum, a.count)
        assert diff[f"{key}_ci"] == pytest.approx(list(block_bootstrap_ci(paired, n_resamples=400)))
    # Paired, the interval is narrower than the two models' own intervals side by side would allow.
    width = diff["energy_m_ci"][1] - diff["energy_m_ci"][0]
    own = [r["energy_m_ci"][1] - r["energy_m_ci"][0] for r in (mine, other)]
    assert width < max(own)
    # The narrower distribution (the stand-in head) is over-confident on these noisy walkers.
    assert diff["nll_m"] > 0 and diff["coverage_90"] == pytest.approx(mine["coverage_90"] - other["coverage_90"])
