"""The paper's Bayesian network: the KL of a layer, the mu/rho split, mean and std maps."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from swarmmap.shared.learning.bnn import BayesLinear, BayesNet, gaussian_kl, is_rho, predict_mean_std, sample_weights
from swarmmap.shared.learning.models import StochasticNet
from swarmmap.shared.learning.networks import build_model, has_std, load_model, save_model
from swarmmap.shared.run.config import model_kinds


def test_layer_kl_matches_a_monte_carlo_estimate():
    torch.manual_seed(0)
    layer = BayesLinear(3, 2, prior_sigma=0.3, rho_init=-1.0)
    with torch.no_grad():
        layer.weight_mu.normal_(0, 0.5)
        layer.weight_rho.uniform_(-2, 0)
    closed = layer.kl().item()
    # KL(q || p) = E_q[log q(w) - log p(w)], estimated from a million draws of every parameter.
    n = 1_000_000
    total = 0.0
    for mu, rho in ((layer.weight_mu, layer.weight_rho), (layer.bias_mu, layer.bias_rho)):
        sigma = F.softplus(rho).detach()
        w = mu.detach() + sigma * torch.randn((n, *mu.shape), dtype=torch.float64)
        log_q = torch.distributions.Normal(mu.detach().double(), sigma.double()).log_prob(w)
        log_p = torch.distributions.Normal(0.0, 0.3).log_prob(w)
        total += (log_q - log_p).mean(0).sum().item()
    assert closed == pytest.approx(total, rel=0.01)


def test_equation_6_for_known_gaussians():
    kl = gaussian_kl(torch.tensor(1.0), torch.tensor(2.0), 0.0, 1.0)
    assert kl.item() == pytest.approx(0.5 * (np.log(1 / 4) + (4 + 1) / 1 - 1))
    assert gaussian_kl(torch.tensor(0.3), torch.tensor(0.7), 0.3, 0.7).item() == pytest.approx(0.0, abs=1e-7)


def test_paper_architecture_and_rho_split():
    net = build_model([2, 256, 256, 256, 256, 256, 1], 5.0, (0, 0, 10, 10), seed=0, kind="bnn")
    assert isinstance(net, BayesNet) and len(net.bayes_layers()) == 4
    names = [n for n, _ in net.named_parameters()]
    rho = [n for n in names if is_rho(n)]
    assert len(rho) == 8 and all(n.endswith(("weight_rho", "bias_rho")) for n in rho)
    n_rho = sum(p.numel() for n, p in net.named_parameters() if is_rho(n))
    assert n_rho == 4 * (256 * 256 + 256)
    out = net(torch.zeros(5, 2))
    assert out.shape == (5,) and ((out > 0) & (out < 1)).all()


def test_mean_and_std_from_many_passes_in_batches(tmp_path):
    net = build_model([2, 32, 32, 1], 5.0, (0, 0, 4, 4), seed=1, kind="bnn", rho_init=-2.0)
    pts = np.random.default_rng(0).uniform(0, 4, size=(1000, 2))
    mean, std = predict_mean_std(net, pts, samples=50, batch=128)
    assert mean.shape == std.shape == (1000,) and (std > 0).all()
    again, _ = predict_mean_std(net, pts, samples=50, batch=333)
    np.testing.assert_allclose(mean[:128], again[:128], atol=0)  # same seed, same draws for the first batch
    save_model(net, tmp_path / "m.pt")
    back = load_model(tmp_path / "m.pt")
    np.testing.assert_array_equal(predict_mean_std(back, pts, samples=5)[0], predict_mean_std(net, pts, samples=5)[0])
    det = build_model([2, 32, 32, 1], 5.0, (0, 0, 4, 4), seed=1)
    assert (predict_mean_std(det, pts)[1] == 0).all()


def test_batched_passes_equal_one_forward_pass_per_weight_draw():
    """The batched map evaluation (sampled weights stacked, SIREN layer shared) gives what S
    ordinary forward passes with the same weight draws give, at any chunking."""
    net = build_model([2, 16, 24, 8, 1], 5.0, (0, 0, 4, 4), seed=3, kind="bnn", rho_init=-1.5)
    pts = np.random.default_rng(1).uniform(0, 4, size=(300, 2))
    mean, std = predict_mean_std(net, pts, samples=7, seed=11, points_per_chunk=37, sample_chunk=3)
    generator = torch.Generator().manual_seed(11)
    draws = []
    for group in (3, 3, 1):  # the passes are drawn per group of sample_chunk, layer by layer
        layers = [sample_weights(layer, group, generator) for layer in net.bayes_layers()]
        for s in range(group):
            h = net.seq[0](torch.as_tensor(pts, dtype=torch.float32) - net.centre)
            for w, b in layers:
                h = torch.relu(h @ w[s] + b[s])
            draws.append(torch.sigmoid(net.seq[-1](h)).squeeze(-1))
    draws = torch.stack(draws).double().detach()
    np.testing.assert_allclose(mean, draws.mean(0).numpy(), atol=1e-6)
    np.testing.assert_allclose(std, draws.std(0, unbiased=False).numpy(), atol=1e-5)
    again = predict_mean_std(net, pts, samples=7, seed=11, sample_chunk=3)
    np.testing.assert_allclose(again[0], mean, atol=1e-6)
    assert std.max() > 0.01, "the draws should disagree at rho -1.5"


def test_logit_spread_is_the_probability_spread_unsquashed():
    """std_of="logit" takes the spread of the same draws before the sigmoid: for narrow draws
    the probability's spread is p (1 - p) times it (the sigmoid's slope), the mean is unchanged."""
    net = build_model([2, 16, 24, 1], 5.0, (0, 0, 4, 4), seed=3, kind="bnn", rho_init=-6.0)
    pts = np.random.default_rng(2).uniform(0, 4, size=(400, 2))
    mean, std_p = predict_mean_std(net, pts, samples=20, seed=5)
    mean_z, std_z = predict_mean_std(net, pts, samples=20, seed=5, std_of="logit")
    np.testing.assert_array_equal(mean, mean_z)
    slope = mean * (1 - mean)
    np.testing.assert_allclose(std_p, slope * std_z, rtol=0.02, atol=1e-6)
    assert (std_z > std_p).all()
    with pytest.raises(ValueError, match="std_of"):
        predict_mean_std(net, pts, std_of="variance")


def test_local_reparameterisation_draws_each_example_from_the_same_gaussian():
    """With the local trick a layer's outputs follow N(x mu_W + mu_b, x^2 sigma_W^2 + sigma_b^2),
    as whole weight draws give; the examples of one batch get independent noise."""
    torch.manual_seed(0)
    plain = BayesLinear(3, 2, rho_init=-1.0)
    local = BayesLinear(3, 2, rho_init=-1.0, local_reparam=True)
    local.load_state_dict(plain.state_dict())
    x = torch.tensor([[0.5, -1.0, 2.0]])
    with torch.no_grad():
        a = torch.cat([plain(x) for _ in range(20000)])
        b = local(x.expand(20000, 3))
    torch.testing.assert_close(a.mean(0), b.mean(0), atol=0.03, rtol=0)
    torch.testing.assert_close(a.std(0), b.std(0), atol=0.03, rtol=0.03)
    with torch.no_grad():
        twice = local(x.expand(2, 3))
    assert not torch.equal(twice[0], twice[1])
    local(x).sum().backward()
    assert local.weight_rho.grad.abs().sum() > 0  # the spread still learns


def test_mc_dropout_network_carries_a_fourier_state_and_reports_a_spread(tmp_path):
    four = build_model([2, 32, 16, 1], 5.0, (0, 0, 4, 4), seed=1)
    drop = build_model([2, 32, 16, 1], 5.0, (0, 0, 4, 4), seed=1, kind="dropout", dropout_p=0.2)
    assert [p.shape for p in drop.parameters()] == [p.shape for p in four.parameters()]  # the same State
    for a, b in zip(drop.parameters(), four.parameters()):
        torch.testing.assert_close(a, b)
    pts = np.random.default_rng(0).uniform(0, 4, size=(500, 2))
    mean, std = predict_mean_std(drop, pts, samples=30, seed=4)
    assert (std > 0).mean() > 0.9
    again = predict_mean_std(drop, pts, samples=30, seed=4, points_per_chunk=37)
    np.testing.assert_allclose(mean, again[0], atol=1e-6)  # a mask per pass for the whole map: any chunking
    # The mean of many passes is close to the network with every unit kept (dropout's scaling).
    many = predict_mean_std(drop, pts, samples=400, seed=1)[0]
    assert np.abs(many - predict_mean_std(four, pts)[0]).mean() < 0.02
    with drop.noise(0):
        p1 = drop(torch.as_tensor(pts[:5], dtype=torch.float32))
    with drop.noise(0):
        p2 = drop(torch.as_tensor(pts[:5], dtype=torch.float32))
    torch.testing.assert_close(p1, p2)
    save_model(drop, tmp_path / "d.pt")
    back = load_model(tmp_path / "d.pt")
    assert back.p == 0.2
    np.testing.assert_array_equal(predict_mean_std(back, pts, samples=5)[1], predict_mean_std(drop, pts, samples=5)[1])
    none = build_model([2, 32, 16, 1], 5.0, (0, 0, 4, 4), seed=1, kind="dropout", dropout_p=0.0)
    assert (predict_mean_std(none, pts, samples=5)[1] == 0).all()


def test_has_std_names_exactly_the_stochastic_models():
    """The observer's std panel and the experiments' uncertainty scores ask ``has_std``: it must
    agree with what each kind of model is."""
    for kind in model_kinds():
        model = build_model([2, 8, 8, 1], 1.0, (0.0, 1.0, 0.0, 1.0), 0, kind)
        assert has_std(kind) == isinstance(model, StochasticNet), kind
    with pytest.raises(ValueError, match="unknown model"):
        has_std("gaussian-process")
