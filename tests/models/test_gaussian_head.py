"""The distribution head: bivariate Gaussian arithmetic against scipy, the head's rollouts against the plain
definition, sampled futures, the online path, and the point path left as it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from crowdnav_mesrnn import load_pretrained
from crowdnav_mesrnn.data import MinMax
from crowdnav_mesrnn.models import gaussian
from crowdnav_mesrnn.models.architecture import MODEL_TYPES, ModelConfig
from crowdnav_mesrnn.models.learned import LearnedPredictor, lean_state, load_predictor
from crowdnav_mesrnn.models.reference import reference_forward
from crowdnav_mesrnn.models.structural_rnn import StructuralRNN

SMALL = {"node_embed": 16, "node_hidden": 24, "edge_embed": 8, "edge_hidden": 12}
RESIDUAL = {"aggregate": "mean", "node_input": "velocity", "offset": "cv_residual"}


def random_net(model: str, seed: int = 0, head: str = "gaussian", **kw) -> StructuralRNN:
    torch.manual_seed(seed)
    net = StructuralRNN(ModelConfig(model=model, head=head, **{**SMALL, **kw}))
    with torch.no_grad():
        for p in net.parameters():
            p.uniform_(-0.5, 0.5)
    return net


def random_batch(b: int = 3, t: int = 20, n: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(torch.randn(b, t, n, 2, generator=g) * 0.05, dim=1) + torch.rand(b, 1, n, 2, generator=g)
    mask = torch.rand(b, t, n, generator=g) < 0.7
    mask[:, :, 0] = True
    mask[:, :, -1] = False
    return torch.where(mask.unsqueeze(-1), pos, torch.full_like(pos, 7.0)), mask


# ------------------------------------------------------------------ the Gaussian arithmetic
def test_nll_mahalanobis_and_radius_agree_with_scipy() -> None:
    rng = np.random.default_rng(0)
    sigma = rng.uniform(0.1, 2.0, (50, 2))
    rho = rng.uniform(-0.9, 0.9, 50)
    err = rng.normal(0, 1.5, (50, 2))
    for i in range(50):
        sx, sy, r = sigma[i, 0], sigma[i, 1], rho[i]
        cov = np.array([[sx * sx, r * sx * sy], [r * sx * sy, sy * sy]])
        want = -stats.multivariate_normal(np.zeros(2), cov).logpdf(err[i])
        assert gaussian.nll(err[i], sigma[i], rho[i]) == pytest.approx(want, rel=1e-10)
        d2 = err[i] @ np.linalg.solve(cov, err[i])
        assert gaussian.squared_mahalanobis(err[i], sigma[i], rho[i]) == pytest.approx(d2, rel=1e-10)
        assert gaussian.major_semi_axis(sigma[i], rho[i]) == pytest.approx(np.sqrt(np.linalg.eigvalsh(cov)[-1]))
    # torch and numpy give the same values
    t = gaussian.nll(torch.from_numpy(err), torch.from_numpy(sigma), torch.from_numpy(rho)).numpy()
    np.testing.assert_allclose(t, gaussian.nll(err, sigma, rho), rtol=1e-12)
    for level in (0.5, 0.9, 0.95):
        assert stats.chi2(2).cdf(gaussian.chi2_radius(level) ** 2) == pytest.approx(level)
    with pytest.raises(ValueError, match=r"coverage level must lie in \(0, 1\)"):
        gaussian.chi2_radius(1.0)


def test_samples_have_the_gaussians_moments_and_coverage() -> None:
    g = torch.Generator().manual_seed(0)
    mean = torch.tensor([[[[1.0, -2.0]]]])  # (B=1, P=1, N=1, 2)
    sigma = torch.tensor([[[[0.5, 2.0]]]])
    rho = torch.tensor([[[0.7]]])
    draws = gaussian.GaussianForecast(mean, sigma, rho).draw(200_000, g)[0, :, 0, 0].double().numpy()
    cov = np.cov(draws.T)
    np.testing.assert_allclose(draws.mean(0), [1.0, -2.0], atol=0.02)
    np.testing.assert_allclose(cov, [[0.25, 0.7], [0.7, 4.0]], rtol=0.02)
    d = np.sqrt(gaussian.squared_mahalanobis(draws - [1.0, -2.0], np.array([0.5, 2.0]), 0.7))
    for level in (0.5, 0.9, 0.95):
        assert np.mean(d <= gaussian.chi2_radius(level)) == pytest.approx(level, abs=0.005)


def test_coherent_draws_keep_each_steps_gaussian_and_one_quantile_along_the_trajectory() -> None:
    g = torch.Generator().manual_seed(1)
    mean = torch.tensor([[[[0.0, 0.0]], [[1.0, 0.0]]]])  # (B=1, P=2, N=1, 2)
    sigma = torch.tensor([[[[0.5, 0.5]], [[1.0, 2.0]]]])
    rho = torch.tensor([[[0.0], [0.5]]])
    draws = gaussian.GaussianForecast(mean, sigma, rho).draw(100_000, g, coherent=True)[0, :, :, 0].double().numpy()
    np.testing.assert_allclose(np.cov(draws[:, 1].T), [[1.0, 1.0], [1.0, 4.0]], rtol=0.03)
    # the first coordinate's standardised value is the same at both steps
    np.testing.assert_allclose(draws[:, 0, 0] / 0.5, draws[:, 1, 0] - 1.0, atol=1e-5)


# ------------------------------------------------------------------ the point path is unchanged
def test_point_configs_read_and_hash_as_before() -> None:
    """A point config's repr and saved dict are those of the code before the head existed: the forecast cache's
    keys (which hash the repr) and the shipped checkpoints' configs stay valid."""
    from envs.forecasting.cache import predictor_fingerprint

    cfg = ModelConfig(model="srnn")
    assert "head" not in repr(cfg) and "head" not in cfg.to_dict()
    assert "head='gaussian'" in repr(ModelConfig(head="gaussian"))
    assert ModelConfig.from_dict(ModelConfig(head="gaussian").to_dict()).head == "gaussian"
    # SHA-256 of the shipped zara1 weights + config, computed with the code before this change
    assert predictor_fingerprint(load_pretrained("mesrnn", "zara1")) == (
        "3b3452a7956ddac106fb46fdadc57a9b652e760ec3a339d10ffa34c895044ca3"
    )
    assert predictor_fingerprint(load_pretrained("vlstm", "zara1")) == (
        "3ae9f0ea28278df271b91e9a86b1a4e7784f0bf45e0cc8113ed3432dc0d66ad2"
    )


@pytest.mark.parametrize("model", list(MODEL_TYPES))
def test_the_heads_mean_is_the_point_networks_forecast(model: str) -> None:
    """The same weights with and without the distribution head forecast the same points, to the bit."""
    g_net = random_net(model, **RESIDUAL).eval()
    p_net = StructuralRNN(ModelConfig(model=model, **{**SMALL, **RESIDUAL})).eval()
    shared = {k: v for k, v in g_net.state_dict().items() if not k.startswith("scale_head") and k != "step_bias"}
    p_net.load_state_dict(shared)
    pos, mask = random_batch()
    with torch.no_grad():
        mean, sigma, rho = g_net.rollout_distribution(pos[:, :8], mask[:, :8], 12)
        assert torch.equal(mean, p_net.rollout(pos[:, :8], mask[:, :8], 12))
        assert torch.equal(g_net(pos, mask, 8)[0], p_net(pos, mask, 8)[0])
    assert sigma.shape == (3, 12, 6, 2) and rho.shape == (3, 12, 6)
    assert torch.all(sigma >= gaussian.SIGMA_MIN) and torch.all(rho.abs() <= gaussian.RHO_MAX)
    with pytest.raises(ValueError, match="point head"):
        p_net.rollout_distribution(pos[:, :8], mask[:, :8], 12)


def test_an_untrained_head_starts_at_the_initial_scale() -> None:
    net = StructuralRNN(ModelConfig(model="srnn", head="gaussian", **SMALL)).eval()
    pos, mask = random_batch()
    with torch.no_grad():
        _, sigma, rho = net.rollout_distribution(pos[:, :8], mask[:, :8], 12)
    torch.testing.assert_close(sigma, torch.full_like(sigma, gaussian.SIGMA_INIT))
    assert torch.all(rho == 0)


# ------------------------------------------------------------------ against the plain definition
@pytest.mark.parametrize("model", list(MODEL_TYPES))
@pytest.mark.parametrize("teacher_forcing", [True, False])
def test_distribution_and_gradients_equal_the_reference(model: str, teacher_forcing: bool) -> None:
    net = random_net(model, **RESIDUAL).train()
    pos, mask = random_batch()
    mean, raw, used = net.forward_distribution(pos, mask, 8, teacher_forcing=teacher_forcing)
    raws: list[torch.Tensor] = []
    ref, ref_used = reference_forward(net, pos, mask, 8, teacher_forcing=teacher_forcing, raws=raws)
    ref_raw = torch.stack(raws, 1)
    torch.testing.assert_close(mean, ref, rtol=1e-5, atol=1e-5)
    assert raw is not None and torch.equal(used, ref_used)
    live = used.unsqueeze(-1).expand_as(raw)  # rows absent at a step carry no output
    torch.testing.assert_close(raw[live], ref_raw[live], rtol=1e-5, atol=1e-5)
    target = torch.rand_like(mean)
    sigma, rho = gaussian.params_from_raw(raw)
    ref_sigma, ref_rho = gaussian.params_from_raw(ref_raw)
    w = used.to(mean.dtype)
    loss = (gaussian.nll(target - mean, sigma, rho) * w).sum()
    ref_loss = (gaussian.nll(target - ref, ref_sigma, ref_rho) * w).sum()
    grads = torch.autograd.grad(loss, list(net.parameters()))
    ref_grads = torch.autograd.grad(ref_loss, list(net.parameters()))
    for (name, _), a, b in zip(net.named_parameters(), grads, ref_grads, strict=True):
        # random weights roll out far from the targets: gradients reach 1e5, so the tolerance is relative to each
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()), msg=name)


@pytest.mark.parametrize("model", list(MODEL_TYPES))
def test_sampled_rollout_feeds_back_samples_as_the_reference_does(model: str) -> None:
    net = random_net(model, seed=1, **RESIDUAL).eval()
    pos, mask = random_batch(seed=1)
    samples = 4
    with torch.no_grad():
        got = net.sample_rollout(pos[:, :8], mask[:, :8], 12, samples, torch.Generator().manual_seed(5))
        g = torch.Generator().manual_seed(5)

        def draw(mean: torch.Tensor, raw: torch.Tensor) -> torch.Tensor:
            sigma, rho = gaussian.params_from_raw(raw)
            return gaussian.sample(mean, sigma, rho, torch.randn(mean.shape, generator=g))

        rep_p = pos[:, :8].repeat_interleave(samples, 0)
        rep_m = mask[:, :8].repeat_interleave(samples, 0)
        full_p = torch.cat([rep_p, rep_p.new_zeros(len(rep_p), 12, 6, 2)], 1)
        full_m = torch.cat([rep_m, torch.zeros(len(rep_m), 12, 6, dtype=torch.bool)], 1)
        want = reference_forward(net, full_p, full_m, 8, teacher_forcing=False, feed=draw)[0][:, 7:]
    assert got.shape == (3, samples, 12, 6, 2)
    roll = mask[:, 7]  # forecasts exist for pedestrians present at the last observed step
    want = want.view(3, samples, 12, 6, 2)
    live = roll[:, None, None, :].expand(-1, samples, 12, -1)
    torch.testing.assert_close(got[live], want[live], rtol=1e-4, atol=1e-4)
    # samples differ from one another and from the mean rollout
    assert not torch.allclose(got[:, 0], got[:, 1])


# ------------------------------------------------------------------ the predictor and its online path
def gaussian_predictor(model: str = "mesrnn") -> LearnedPredictor:
    return LearnedPredictor(random_net(model, **RESIDUAL), MinMax((0.0, 0.0), (10.0, 20.0)))


@pytest.mark.parametrize("model", list(MODEL_TYPES))
def test_online_distribution_equals_from_scratch(model: str) -> None:
    pred = gaussian_predictor(model)
    rng = np.random.default_rng(1)
    hist = np.cumsum(rng.normal(0.3, 0.1, size=(8, 5, 2)), axis=0).astype(np.float32) + 2
    mask = rng.uniform(size=(8, 5)) < 0.8
    mask[-1, :2] = True
    mask[-1, 4] = False
    online = pred.online(5)
    for t in range(8):
        online.observe(hist[t], mask[t])
    got = online.forecast_distribution()
    want = pred.forecast_distribution(hist, mask)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(got[0], pred.forecast(hist, mask), rtol=1e-5, atol=1e-4)
    assert np.all(got[1][~mask[-1]] == 0) and np.all(got[1][mask[-1]] > 0)


def test_scales_are_in_metres_per_axis() -> None:
    """The head's scales are in normalised units; the predictor returns metres (x range 10 m, y range 20 m)."""
    pred = gaussian_predictor("vlstm")
    pos, mask = random_batch(b=1)
    dist = pred.predict_distribution_batch(pos * 10, mask)
    with torch.no_grad():
        normed = torch.where(mask[:, :8, :, None], pred.norm.normalise(pos[:, :8] * 10), 0.0)
        _, sigma_n, rho_n = pred.net.rollout_distribution(normed, mask[:, :8], 12)
    torch.testing.assert_close(dist.sigma, sigma_n * torch.tensor([5.0, 10.0]))
    torch.testing.assert_close(dist.rho, rho_n)


def test_point_predictors_refuse_a_distribution() -> None:
    pred = load_pretrained("vlstm", "zara1")
    assert not pred.has_distribution
    with pytest.raises(ValueError, match="point head: it forecasts no distribution"):
        pred.forecast_distribution(np.zeros((8, 2, 2), np.float32), np.ones((8, 2), bool))
    with pytest.raises(ValueError, match="point head"):
        pred.online(2).forecast_distribution()


def test_marginal_and_feedback_samples(tmp_path: Path) -> None:
    pred = gaussian_predictor("srnn")
    pos, mask = random_batch(b=2)
    mask[:, :8, :3] = True
    marginal = pred.sample_batch(pos, mask, 3, torch.Generator().manual_seed(0))
    feedback = pred.sample_batch(pos, mask, 3, torch.Generator().manual_seed(0), feedback=True)
    assert marginal.shape == feedback.shape == (2, 3, 12, 6, 2)
    assert not torch.allclose(marginal[:, :, 1:, :3], feedback[:, :, 1:, :3])
    again = pred.sample_batch(pos, mask, 3, torch.Generator().manual_seed(0))
    assert torch.equal(marginal, again)  # seeded
    # A checkpoint with the head round-trips
    ck = {
        "model_config": pred.net.cfg.to_dict(),
        "state_dict": lean_state(pred.net),
        "norm": pred.norm.to_dict(),
        "train_config": {"split": "zara1"},
    }
    torch.save(ck, tmp_path / "g.pt")
    loaded = load_predictor(tmp_path / "g.pt", model="srnn")
    assert loaded.has_distribution
    torch.testing.assert_close(
        loaded.predict_distribution_batch(pos, mask).sigma, pred.predict_distribution_batch(pos, mask).sigma
    )


# ------------------------------------------------------------------ the dense step of the rollout
@pytest.mark.parametrize("model", list(MODEL_TYPES))
@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_features_without_masks_equal_the_masked_ones_to_the_bit(model: str, aggregate: str) -> None:
    """With everyone present the rollout skips the masks (``m=None``); the features must not move by one bit."""
    net = random_net(model, aggregate=aggregate, feature_scale=0.7)
    g = torch.Generator().manual_seed(3)
    p = tuple(torch.randn(2, 7, 2, generator=g) for _ in range(3))
    ones = torch.ones(2, 7, dtype=torch.bool)
    feats, vel = net._features(p, (ones, ones, ones))
    dense_feats, dense_vel = net._features(p, None)
    assert torch.equal(vel, dense_vel)
    assert (feats is None) == (dense_feats is None)
    if feats is not None:
        assert dense_feats is not None and torch.equal(feats, dense_feats)


def crowd_sequence(t_len: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random walks in metres (zara1-sized area) with pedestrians entering, leaving and coming back."""
    rng = np.random.default_rng(seed)
    pos = (np.cumsum(rng.normal(0.0, 0.25, size=(t_len, n, 2)), axis=0) + rng.uniform(2, 12, (1, n, 2))).astype(
        np.float32
    )
    mask = np.ones((t_len, n), bool)
    for j in range(n):
        if j % 3 == 0:  # enters late
            mask[: rng.integers(1, t_len // 2), j] = False
        if j % 5 == 0:  # leaves early
            mask[rng.integers(t_len // 2, t_len) :, j] = False
        if j % 7 == 0:  # a gap
            g = rng.integers(2, t_len - 3)
            mask[g : g + 2, j] = False
    return pos, mask


@pytest.mark.parametrize("head", ["point", "gaussian"])
def test_incremental_forecasts_equal_from_scratch_with_50_pedestrians(head: str) -> None:
    """Frame after frame of a 50-pedestrian crowd (entries, exits, gaps), the online forecaster's forecast equals
    the structural RNN run from scratch over every frame so far, to float32 rounding; the shipped MESRNN's
    weights (point head), or the same weights with a random distribution head."""
    shipped = load_pretrained("mesrnn", "zara1")
    if head == "point":
        pred = shipped
    else:
        net = StructuralRNN(ModelConfig.from_dict({**shipped.net.cfg.to_dict(), "head": "gaussian"}))
        torch.manual_seed(0)
        head = {k: torch.randn_like(v) * 0.1 for k, v in net.state_dict().items() if k not in shipped.net.state_dict()}
        net.load_state_dict({**shipped.net.state_dict(), **head})
        pred = LearnedPredictor(net, shipped.norm)
    pos, mask = crowd_sequence(30, 50, seed=3)
    online = pred.online(50)
    normed = torch.where(torch.from_numpy(mask)[..., None], pred.norm.normalise(torch.from_numpy(pos)), 0.0)
    checked = 0
    for t in range(30):
        online.observe(pos[t], mask[t])
        if t < 7 or t % 4:
            continue
        with torch.no_grad():
            mean, raw, _ = pred.net.forward_distribution(
                torch.cat([normed[None, : t + 1], torch.zeros(1, 12, 50, 2)], 1),
                torch.cat([torch.from_numpy(mask)[None, : t + 1], torch.zeros(1, 12, 50, dtype=torch.bool)], 1),
                t + 1,
                teacher_forcing=False,
            )
        live = mask[t]
        want = pred.norm.denormalise(mean[0, t:]).permute(1, 0, 2).numpy()
        if head == "point":
            got = online.forecast()
        else:
            got, sigma, rho = online.forecast_distribution()
            want_sigma, want_rho = gaussian.params_from_raw(raw[0, t:])
            np.testing.assert_allclose(
                sigma[live],
                (want_sigma / torch.tensor(pred.norm.scale, dtype=torch.float32)).permute(1, 0, 2).numpy()[live],
                rtol=1e-4,
                atol=1e-5,
            )
            np.testing.assert_allclose(rho[live], want_rho.permute(1, 0).numpy()[live], rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(got[live], want[live], rtol=0, atol=1e-4)
        checked += int(live.sum())
    assert checked > 200


def test_networks_copy_and_pickle_after_online_use() -> None:
    import copy
    import pickle

    pred = load_pretrained("srnn", "zara1")
    online = pred.online(10)
    pos, mask = crowd_sequence(9, 10, seed=1)
    for t in range(9):
        online.observe(pos[t], mask[t])
    online.forecast()
    assert pred.net._online is not None  # the derived weights exist
    twin = pickle.loads(pickle.dumps(copy.deepcopy(pred.net)))
    assert twin._online is None and twin._prepared is None
    x = torch.zeros(1, 8, 3, 2)
    m = torch.ones(1, 8, 3, dtype=torch.bool)
    with torch.no_grad():
        assert torch.equal(twin.rollout(x, m, 12), pred.net.rollout(x, m, 12))


def test_scale_detach_keeps_the_scales_gradient_out_of_the_trunk() -> None:
    pos, mask = random_batch()
    for detach in (False, True):
        net = random_net("srnn", scale_detach=detach, **RESIDUAL).train()
        _, raw, _ = net.forward_distribution(pos, mask, 8, teacher_forcing=False)
        assert raw is not None
        grads = torch.autograd.grad(raw.sum(), [net.node_cell.weight_hh, net.scale_head.weight], allow_unused=True)
        assert grads[1] is not None and grads[1].abs().sum() > 0
        trunk = grads[0]
        assert (trunk is None or trunk.abs().sum() == 0) == detach
    with pytest.raises(Exception, match="scale_detach needs head: gaussian"):
        ModelConfig(scale_detach=True)
    assert "scale_detach" not in repr(ModelConfig()) and "scale_detach" not in ModelConfig().to_dict()


@pytest.mark.parametrize("n", [1, 2, 7, 50])
def test_linear_time_meta_paths_equal_the_pairwise_sums(n: int) -> None:
    from crowdnav_mesrnn.graph.metapaths import METAPATH_TYPES, dense_features_centred, stacked_features_step

    g = torch.Generator().manual_seed(n)
    p = [torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1 for _ in range(3)]
    want, want_vel = stacked_features_step(*p, None, None, None, METAPATH_TYPES)
    got, vel, factors = dense_features_centred(*p, METAPATH_TYPES)
    assert factors == tuple(float(n) if t in ("S", "SS", "TS") else 1.0 for t in METAPATH_TYPES)
    f = torch.tensor(factors, dtype=torch.float64)[:, None, None]
    torch.testing.assert_close(got * f, want, rtol=1e-12, atol=1e-12)  # exact algebra (float64)
    assert torch.equal(vel, want_vel)
    f32, _, _ = dense_features_centred(*(x.float() for x in p), METAPATH_TYPES)
    scale = want.abs().amax(dim=(1, 2), keepdim=True).clamp(min=1.0)
    assert float(((f32.double() * f - want) / scale).abs().max()) < 1e-5  # float32: rounding only
    sub, _, sub_f = dense_features_centred(*p, ("TT", "SS"))  # any subset, in the order asked
    assert sub_f == (1.0, float(n))
    torch.testing.assert_close(sub * torch.tensor(sub_f, dtype=torch.float64)[:, None, None], want[[5, 2]])
