"""``cv_gaussian``: the fit against known scales and closed forms, the NLL against scipy, the selection rule,
coherent and marginal samples, the mean against constant velocity, and the parameter files (shipped and malformed)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from crowdnav_mesrnn.data.constants import OBS_LEN, PRED_LEN, SPLITS
from crowdnav_mesrnn.data.windows import Window, split_windows
from crowdnav_mesrnn.evaluation.metrics import collect_forecasts
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.base import ConstantVelocity
from crowdnav_mesrnn.models.cv_gaussian import (
    CvGaussian,
    CvGaussianParams,
    CvGaussianParamsError,
    isotropic_nll,
    load_cv_gaussian,
    load_params,
    params_path,
)
from crowdnav_mesrnn.models.cv_gaussian_fit import (
    SELECTION_TOLERANCE_NATS,
    StepStats,
    fit_candidates,
    fit_form,
    main,
    mean_nll,
    select_form,
    window_stats,
    write_params,
)

H = np.arange(1, PRED_LEN + 1, dtype=np.float64)


def synthetic_windows(a: float, b: float, windows: int, peds: int = 4, seed: int = 0) -> list[Window]:
    """Walkers on straight lines at constant velocity for the 8 observed steps, whose 12 future positions are the
    constant-velocity forecast plus isotropic noise of scale ``a + b·h``: data drawn from the model itself.
    One context pedestrian per window is absent from the last steps (never scored)."""
    rng = np.random.default_rng(seed)
    t = OBS_LEN + PRED_LEN
    out = []
    for i in range(windows):
        start = rng.uniform(-5, 5, (peds, 2))
        vel = rng.normal(0, 0.4, (peds, 2))
        k = np.arange(t)[:, None, None]
        pos = start[None] + k * vel[None]
        noise = rng.normal(0, 1, (PRED_LEN, peds, 2)) * (a + b * H)[:, None, None]
        pos[OBS_LEN:] += noise
        present = np.ones((t, peds), bool)
        present[-3:, -1] = False
        out.append(
            Window(
                positions=np.where(present[..., None], pos, 0.0).astype(np.float64),
                present=present,
                scored=present.all(axis=0),
                recording="synthetic_train",
                start_frame=10 * i,
                ped_ids=np.arange(peds),
            )
        )
    return out


def stats_from_model(a: float, b: float, rows: int, seed: int) -> StepStats:
    rng = np.random.default_rng(seed)
    return StepStats.from_errors(rng.normal(0, 1, (rows, PRED_LEN, 2)) * (a + b * H)[None, :, None])


# ------------------------------------------------------------------ the NLL
def test_nll_matches_the_closed_form_on_a_tiny_example() -> None:
    a, b = 0.1, 0.05
    err = np.array([[[0.03, 0.04], [0.0, -0.2]]])  # one pedestrian, two steps: |e|² = 0.0025, 0.04
    sigma = np.array([a + b, a + 2 * b])  # 0.15, 0.2
    by_hand = [
        math.log(2 * math.pi * 0.15**2) + 0.0025 / (2 * 0.15**2),
        math.log(2 * math.pi * 0.2**2) + 0.04 / (2 * 0.2**2),
    ]
    got = isotropic_nll(err, sigma[None])
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got[0], by_hand, rtol=1e-12)
    for j in range(2):
        want = -stats.multivariate_normal(np.zeros(2), sigma[j] ** 2 * np.eye(2)).logpdf(err[0, j])
        assert got[0, j] == pytest.approx(want, rel=1e-12)
    # the sufficient-statistic NLL of the fit is the mean of the same terms; torch gives the same
    st = StepStats(np.array([1, 1]), np.array([0.0025, 0.04]))
    assert mean_nll(st, a, b) == pytest.approx(np.mean(by_hand), rel=1e-12)
    t = isotropic_nll(torch.from_numpy(err), torch.from_numpy(sigma[None])).numpy()
    np.testing.assert_allclose(t, got, rtol=1e-12)


def test_model_nll_through_the_evaluation_path_equals_the_fits_objective() -> None:
    windows = synthetic_windows(0.05, 0.04, 60, seed=1)
    model = CvGaussian(CvGaussianParams(0.07, 0.03))
    scored = collect_forecasts(windows, distribution=model.predict_distribution_batch)
    assert scored.sigma is not None and scored.rho is not None
    via_eval = float(gaussian.nll(scored.error, scored.sigma, scored.rho).mean())
    assert np.isfinite(via_eval)
    assert via_eval == pytest.approx(mean_nll(window_stats(windows), 0.07, 0.03), rel=1e-6)  # float32 scales


# ------------------------------------------------------------------ the fit
@pytest.mark.parametrize(("a", "b"), [(0.08, 0.06), (0.0, 0.065), (0.3, 0.0)])
def test_fit_recovers_known_scales_from_windows_drawn_from_the_model(a: float, b: float) -> None:
    fitted_a, fitted_b = fit_form(window_stats(synthetic_windows(a, b, 1500, seed=2)), "a+b*h")
    # 18 000 scored pedestrians x 12 steps: the MLE is within ~1 % of a scale; 0 lands near the bound
    assert fitted_a == pytest.approx(a, abs=0.004)
    assert fitted_b == pytest.approx(b, abs=0.001)


def test_one_parameter_fits_are_the_closed_form_maxima() -> None:
    st = stats_from_model(0.1, 0.05, 3000, seed=3)
    a, _ = fit_form(st, "a")
    _, b = fit_form(st, "b*h")
    for form, (x, y), free in (("a", (a, 0.0), 0), ("b*h", (0.0, b), 1)):
        # a maximum: every nearby value of the free parameter is worse
        for d in (-1e-3, 1e-3):
            moved = (x + d, y) if free == 0 else (x, y + d)
            assert mean_nll(st, *moved) > mean_nll(st, x, y), form
    # the two-parameter fit contains both, so it is at least as good on the data it was fitted on
    full = fit_form(st, "a+b*h")
    assert mean_nll(st, *full) <= min(mean_nll(st, a, 0.0), mean_nll(st, 0.0, b)) + 1e-12
    # and it is a stationary point: scipy's own numerical minimisation from elsewhere finds the same
    from scipy import optimize

    res = optimize.minimize(lambda x: mean_nll(st, *x), [0.3, 0.01], method="Nelder-Mead", options={"xatol": 1e-9})
    np.testing.assert_allclose(full, res.x, atol=1e-5)


@pytest.mark.parametrize(("a", "b", "form"), [(0.12, 0.05, "a+b*h"), (0.0, 0.06, "b*h"), (0.35, 0.0, "a")])
def test_selection_picks_the_true_form(a: float, b: float, form: str) -> None:
    picks = []
    for seed in range(3):
        train = stats_from_model(a, b, 3000, seed=10 + seed)
        val = stats_from_model(a, b, 800, seed=100 + seed)
        cands = fit_candidates(train, val)
        picks.append(select_form({f: c["val_nll"] for f, c in cands.items()}))
    assert picks == [form] * 3


def test_selection_rule_tolerance() -> None:
    t = SELECTION_TOLERANCE_NATS
    assert select_form({"a+b*h": 1.0, "b*h": 1.0 + 0.5 * t, "a": 1.5}) == "b*h"
    assert select_form({"a+b*h": 1.0, "b*h": 1.0 + 2 * t, "a": 1.5}) == "a+b*h"
    assert select_form({"a+b*h": 1.0, "b*h": 1.2, "a": 1.0 + 0.5 * t}) == "a"
    assert select_form({"a+b*h": 1.0, "b*h": 0.9, "a": 1.5}) == "b*h"
    with pytest.raises(ValueError, match="'a'"):
        select_form({"a+b*h": 1.0, "b*h": 1.0, "a": math.nan})


# ------------------------------------------------------------------ mean and sampling
def batch(b: int = 3, n: int = 5, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(torch.randn(b, OBS_LEN + PRED_LEN, n, 2, generator=g) * 0.1, dim=1)
    mask = torch.rand(b, OBS_LEN + PRED_LEN, n, generator=g) < 0.8
    mask[:, :, 0] = True
    return torch.where(mask.unsqueeze(-1), pos, torch.zeros_like(pos)), mask


def test_mean_is_constant_velocity_and_scale_grows_linearly() -> None:
    model = CvGaussian(CvGaussianParams(0.1, 0.05))
    pos, mask = batch()
    dist = model.predict_distribution_batch(pos, mask)
    cv = ConstantVelocity()
    for i in range(pos.shape[0]):
        want = cv.forecast(pos[i, :OBS_LEN].numpy(), mask[i, :OBS_LEN].numpy())  # (N, P, 2)
        np.testing.assert_array_equal(dist.mean[i].permute(1, 0, 2).numpy(), want)
        np.testing.assert_array_equal(model.forecast(pos[i, :OBS_LEN].numpy(), mask[i, :OBS_LEN].numpy()), want)
        mean, sigma, rho = model.forecast_distribution(pos[i, :OBS_LEN].numpy(), mask[i, :OBS_LEN].numpy())
        np.testing.assert_array_equal(mean, want)
        here = mask[i, OBS_LEN - 1].numpy()
        np.testing.assert_allclose(sigma[here], np.broadcast_to((0.1 + 0.05 * H)[:, None], (here.sum(), 12, 2)))
        assert np.all(sigma[~here] == 0) and np.all(rho == 0)
    assert dist.sigma.shape == (3, PRED_LEN, 5, 2) and dist.rho.shape == (3, PRED_LEN, 5)
    np.testing.assert_allclose(dist.sigma[0, :, 0, 0].numpy(), 0.1 + 0.05 * H, rtol=1e-6)
    assert torch.all(dist.rho == 0)


def test_coherent_samples_share_one_draw_across_steps_marginal_do_not() -> None:
    model = CvGaussian(CvGaussianParams(0.1, 0.05))
    pos, mask = batch()
    mean = model.predict_batch(pos, mask)
    scale = torch.as_tensor(0.1 + 0.05 * H, dtype=torch.float32).view(1, 1, PRED_LEN, 1, 1)
    for coherent in (True, False):
        draws = model.sample_batch(pos, mask, 7, torch.Generator().manual_seed(0), coherent=coherent)
        assert draws.shape == (3, 7, PRED_LEN, 5, 2)
        z = (draws - mean[:, None]) / scale  # the standard normal draw behind each position
        spread = (z - z[:, :, :1]).abs().amax(dim=2)  # how far each step's draw is from step 1's
        if coherent:
            assert float(spread.max()) < 1e-4
        else:
            assert float(spread.min()) > 1e-3
    with pytest.raises(ValueError, match="feedback"):
        model.sample_batch(pos, mask, 2, feedback=True)


def test_marginal_and_coherent_samples_have_each_steps_scale() -> None:
    model = CvGaussian(CvGaussianParams(0.2, 0.1))
    pos, mask = batch(b=1, n=1)
    mean = model.predict_batch(pos, mask)
    for coherent in (True, False):
        draws = model.sample_batch(pos, mask, 20000, torch.Generator().manual_seed(1), coherent=coherent)
        std = (draws - mean[:, None]).std(dim=1)[0, :, 0]  # (P, 2)
        np.testing.assert_allclose(std.numpy(), np.broadcast_to((0.2 + 0.1 * H)[:, None], (12, 2)), rtol=0.03)


def test_params_reject_bad_values() -> None:
    for kw, key in (
        ({"a_m": -0.1, "b_m": 0.1}, "a_m"),
        ({"a_m": 0.1, "b_m": math.inf}, "b_m"),
        ({"a_m": 0.0, "b_m": 0.0}, "a_m \\+ b_m"),
        ({"a_m": 0.1, "b_m": 0.1, "form": "a"}, "form 'a'"),
        ({"a_m": 0.1, "b_m": 0.1, "form": "quadratic"}, "form"),
    ):
        with pytest.raises(ValueError, match=key):
            CvGaussianParams(**kw)


# ------------------------------------------------------------------ parameter files
def good_record(split: str = "zara1") -> dict:
    cands = {
        "a+b*h": {"a_m": 0.05, "b_m": 0.06, "train_nll": -1.0, "val_nll": -1.1},
        "b*h": {"a_m": 0.0, "b_m": 0.065, "train_nll": -0.9, "val_nll": -1.0},
        "a": {"a_m": 0.4, "b_m": 0.0, "train_nll": 0.5, "val_nll": 0.6},
    }
    return {
        "format": 1,
        "model": "cv_gaussian",
        "split": split,
        "form": "a+b*h",
        "a_m": 0.05,
        "b_m": 0.06,
        "candidates": cands,
        "selection": {},
        "data": {},
        "fit": {},
        "code_version": "test",
    }


def test_a_good_file_loads(tmp_path: Path) -> None:
    path = params_path("zara1", tmp_path)
    path.write_text(json.dumps(good_record()))
    model = load_cv_gaussian("zara1", tmp_path)
    assert model.name == "cv_gaussian" and model.split == "zara1" and model.info["code_version"] == "test"
    np.testing.assert_allclose(model.sigma_m(), 0.05 + 0.06 * H)


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda r: r.pop("b_m"), "'b_m'"),
        (lambda r: r.update(b_m=-0.01), "'b_m'"),
        (lambda r: r.update(a_m=float("nan")), "'a_m'"),
        (lambda r: r.update(a_m="0.05"), "'a_m'"),
        (lambda r: r.update(a_m=0.0, b_m=0.0), "'a_m' and 'b_m'"),
        (lambda r: r.update(form="b*h"), "'a_m' must be 0 under form 'b\\*h'"),
        (lambda r: r.update(form="cubic"), "'form'"),
        (lambda r: r.update(split="eth"), "'split'"),
        (lambda r: r.update(model="cv"), "'model'"),
        (lambda r: r.update(format=2), "'format'"),
        (lambda r: r["candidates"].pop("a"), "'candidates.a'"),
        (lambda r: r["candidates"]["b*h"].update(val_nll=math.inf), "'candidates.b\\*h.val_nll'"),
        (lambda r: r["candidates"]["a+b*h"].update(b_m=0.07), "differ from the selected candidate"),
    ],
)
def test_loading_rejects_a_malformed_file_naming_the_key(tmp_path: Path, edit, key: str) -> None:
    record = good_record()
    edit(record)
    path = params_path("zara1", tmp_path)
    path.write_text(json.dumps(record))  # json writes NaN/Infinity, which Python's reader accepts: the check must not
    with pytest.raises(CvGaussianParamsError, match=key) as info:
        load_params(path, "zara1")
    assert str(path) in str(info.value)


def test_loading_a_missing_or_broken_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(CvGaussianParamsError, match="cv_gaussian_fit"):
        load_cv_gaussian("eth", tmp_path)
    params_path("eth", tmp_path).write_text("{not json")
    with pytest.raises(CvGaussianParamsError, match="not valid JSON"):
        load_cv_gaussian("eth", tmp_path)


def test_write_params_is_validated_and_round_trips(tmp_path: Path) -> None:
    path = write_params(good_record("hotel"), tmp_path)
    assert path == params_path("hotel", tmp_path) and not list(tmp_path.glob(".*.tmp"))
    assert load_params(path, "hotel")[1] == good_record("hotel")
    bad = good_record("univ") | {"b_m": -1.0}
    with pytest.raises(CvGaussianParamsError, match="'b_m'"):
        write_params(bad, tmp_path)
    assert not params_path("univ", tmp_path).exists()


# ------------------------------------------------------------------ ETH/UCY (shipped files and the command)
@pytest.mark.parametrize("split", SPLITS)
def test_shipped_parameters_load(split: str) -> None:
    model = load_cv_gaussian(split)
    assert model.split == split
    assert np.all(np.isfinite(model.sigma_m())) and np.all(model.sigma_m() > 0)
    held_out = set(model.info["data"]["held_out_never_read"])
    for part in ("train", "val"):
        files = [f["file"] for f in model.info["data"][part]["files"]]
        assert files and not any(Path(f).stem.removesuffix(f"_{part}") in held_out for f in files)


def test_command_reproduces_the_shipped_file_and_its_nll_is_the_evaluations(data_dir: Path, tmp_path: Path) -> None:
    assert main(["--split", "hotel", "--out-dir", str(tmp_path), "--data-dir", str(data_dir)]) == 0
    _, fresh = load_params(params_path("hotel", tmp_path), "hotel")
    shipped = load_cv_gaussian("hotel")
    assert {k: v for k, v in fresh.items() if k != "code_version"} == {
        k: v for k, v in shipped.info.items() if k != "code_version"
    }
    # the shipped validation NLL is what the project's evaluation computes for the shipped model
    val = split_windows("hotel", "val", min_scored=2, data_dir=data_dir)
    scored = collect_forecasts(val, distribution=shipped.predict_distribution_batch)
    assert scored.sigma is not None and scored.rho is not None
    nll = float(gaussian.nll(scored.error, scored.sigma, scored.rho).mean())
    assert nll == pytest.approx(shipped.info["candidates"][shipped.params.form]["val_nll"], rel=1e-6)
