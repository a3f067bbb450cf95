"""The node update: DiNNO on FourierNets, the three regularisation strategies on BNNs, and
the in-process run that the Zenoh run must equal."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from swarmmap.services.learner.consensus.ramen import ramen_targets
from swarmmap.services.learner.consensus.sigma import sigma_pairs, sigma_targets
from swarmmap.services.learner.metrics import validation_bce
from swarmmap.services.learner.registry import node_for
from swarmmap.shared.learning.graphs import neighbour_sets
from swarmmap.shared.learning.layout import state_copies
from swarmmap.shared.learning.networks import build_network
from swarmmap.shared.run.config import LearnerSettings, RunConfig

BOUNDS = (0.0, 0.0, 4.0, 4.0)


def toy_data(node: int, n: int = 3000):
    """Points of a 4 x 4 m box with a wall along x = 2: each node sees a different strip."""
    rng = np.random.default_rng(node)
    x = rng.uniform(0, 4, size=(n, 2)).astype(np.float32)
    x[:, 1] = (x[:, 1] + node * 4 / 3) % 4
    y = (np.abs(x[:, 0] - 2.0) < 0.15).astype(np.float32)
    return torch.from_numpy(x), torch.from_numpy(y)


def network(s: LearnerSettings, seed: int = 0):
    """The network of the learner's settings ``s`` (every node of a run starts from the same one)."""
    return build_network(RunConfig(learner=s).network(), BOUNDS, seed)


def node(s: LearnerSettings, i: int, seed: int, data=None, **kw):
    """Node ``i`` of a run of ``s`` on its toy data (or ``data``)."""
    return node_for(s, network(s), *(data if data is not None else toy_data(i)), seed, **kw)


def run_inproc(settings: LearnerSettings, nodes: int = 3, rounds: int = 6):
    dn = [node(settings, i, seed=i + 1) for i in range(nodes)]
    th = {i: dn[i].state() for i in range(nodes)}
    for k in range(rounds):
        th = {i: dn[i].update(k, th[i], {j: th[j] for j in range(nodes) if j != i}) for i in range(nodes)}
    return dn, th


@pytest.mark.parametrize("strategy", ["uniform-l2", "separate-l2", "separate-kl"])
def test_each_bnn_strategy_trains_and_agrees(strategy):
    s = LearnerSettings(model="bnn", model_shape=[2, 32, 32, 32, 1], regularization=strategy, rounds=30,
                        primal_iterations=5, batch_size=512, lr_start=1e-2, lr_finish=1e-3, rho_init=0.1)
    val_x, val_y = toy_data(9)
    before = validation_bce(network(s), val_x, val_y)
    dn, th = run_inproc(s, rounds=30)
    after = [validation_bce(n.model, val_x, val_y) for n in dn]
    assert max(after) < before
    assert len(dn[0].optimizers or dn[0]._optimizers(1e-3)) == (1 if strategy == "uniform-l2" else 2)


def test_algorithm2_splits_mu_and_rho_into_two_optimizers():
    s = LearnerSettings(model="bnn", model_shape=[2, 16, 8, 1], regularization="separate-kl", optimizer_per_round=False)
    n = node(s, 0, seed=1)
    mu_opt, rho_opt = n.optimizers
    mu_ids = {id(p) for g in mu_opt.param_groups for p in g["params"]}
    rho_names = {k for k, p in n.model.named_parameters() if id(p) in {id(q) for g in rho_opt.param_groups for q in g["params"]}}
    assert rho_names == {"seq.1.weight_rho", "seq.1.bias_rho"}
    assert not mu_ids & {id(p) for g in rho_opt.param_groups for p in g["params"]}
    assert type(n.reg).__name__ == "Algorithm2"
    n_rho = int(n.reg.rho_mask.sum())
    assert (n.reg.rho_mask.numel() - n_rho, n_rho) == (2 * 16 + 16 + 16 * 8 + 8 + 8 + 1, 16 * 8 + 8)


def test_kl_strategy_pulls_spreads_not_means():
    """With identical means and different rho, separate-kl's penalty is the KL of the spreads only."""
    s = LearnerSettings(model="bnn", model_shape=[2, 4, 4, 1], regularization="separate-kl")
    n = node(s, 0, seed=1)
    th = torch.from_numpy(n.state())
    other = th.clone()
    other[n.reg.rho_mask] += 1.0
    reg = (th + other)[None] / 2
    pen = n.reg.penalty(n.rho, th, reg, None).item()
    sig0 = torch.nn.functional.softplus(th[n.reg.rho_mask])
    sig1 = torch.nn.functional.softplus(reg[0, n.reg.rho_mask])
    expected = n.rho * float((torch.log(sig1 / sig0) + sig0**2 / (2 * sig1**2) - 0.5).sum())
    assert pen == pytest.approx(expected, rel=1e-5)


def test_kept_optimizer_differs_from_fresh_one_per_round():
    fresh = LearnerSettings(model_shape=[2, 16, 16, 1], rounds=5, batch_size=256)
    kept = fresh.model_copy(update={"optimizer_per_round": False})
    _, a = run_inproc(fresh, rounds=5)
    _, b = run_inproc(kept, rounds=5)
    assert not np.allclose(a[0], b[0])


def run_baseline(settings, nodes=3, rounds=20):
    graph = neighbour_sets("ring", nodes)
    dn = [node(settings, i, i + 1, graph=graph, robot=i) for i in range(nodes)]
    st = {i: dn[i].state() for i in range(nodes)}
    for k in range(rounds):
        st = {i: dn[i].update(k, st[i], {j: st[j] for j in graph[i]}) for i in range(nodes)}
    return dn, st


@pytest.mark.parametrize("name", ["dsgd", "dsgt"])
def test_dsgd_and_dsgt_learn(name):
    s = LearnerSettings(model_shape=[2, 32, 32, 1], batch_size=512, lr_start=0.3, lr_finish=0.3, rounds=40, algorithm=name)
    val_x, val_y = toy_data(9)
    before = validation_bce(network(s), val_x, val_y)
    dn, _ = run_baseline(s, rounds=40)
    assert max(validation_bce(n.model, val_x, val_y) for n in dn) < before


@pytest.mark.parametrize("name", ["dsgd", "dsgt"])
def test_dsgd_and_dsgt_take_local_steps_between_exchanges(name):
    """exchange_every 2: every other round mixes nothing. The local round moves the node's own
    parameters by a gradient step (DSGT: along its tracker, which takes in the new gradient)."""
    s = LearnerSettings(model_shape=[2, 32, 32, 1], batch_size=512, lr_start=0.3, lr_finish=0.3, rounds=40, algorithm=name,
                        exchange_every=2)
    graph = neighbour_sets("ring", 3)
    dn = [node(s, i, i + 1, graph=graph, robot=i) for i in range(3)]
    val_x, val_y = toy_data(9)
    before = validation_bce(dn[0].model, val_x, val_y)
    st = {i: dn[i].state().copy() for i in range(3)}
    for k in range(40):
        if k % 2:
            st = {i: dn[i].local_update(k, st[i]).copy() for i in range(3)}
        else:
            st = {i: dn[i].update(k, st[i], {j: st[j] for j in graph[i]}).copy() for i in range(3)}
    assert max(validation_bce(n.model, val_x, val_y) for n in dn) < before
    own = st[0].copy()
    moved = dn[0].local_update(40, own).copy()
    n = dn[0].layout.param_count
    assert not np.allclose(moved[:n], own[:n])
    if name == "dsgt":  # theta <- theta - alpha y with the tracker of the State it started from
        np.testing.assert_allclose(moved[:n], own[:n] - 0.3 * own[n:], rtol=1e-5, atol=1e-6)


def test_dsgt_tracks_the_average_gradient():
    """Gradient tracking's invariant with doubly stochastic weights: mean_i y_i = mean_i g_i."""
    s = LearnerSettings(model_shape=[2, 8, 8, 1], batch_size=64, lr_start=0.1, lr_finish=0.1, rounds=5, algorithm="dsgt")
    dn, _ = run_baseline(s, rounds=5)
    mean_y = torch.stack([n.y for n in dn]).mean(0)
    mean_g = torch.stack([n.g_old for n in dn]).mean(0)
    torch.testing.assert_close(mean_y, mean_g, rtol=1e-4, atol=1e-5)


# ----------------------------------------------------------------------------- consensus weights


def bnn_settings(**over):
    base = dict(model="bnn", model_shape=[2, 16, 8, 1], rounds=20, primal_iterations=3, batch_size=256, rho_init=0.1)
    return LearnerSettings(**(base | over))


def test_sigma_consensus_moves_the_less_sure_node_towards_the_surer_one():
    s = bnn_settings(consensus="sigma")
    model = network(s)
    mu_at, rho_at = sigma_pairs(model)
    th_i = torch.nn.utils.parameters_to_vector(model.parameters()).detach()
    th_j = th_i + 1.0
    th_j[rho_at] = th_i[rho_at]  # equally sure: DiNNO's midpoint and weight everywhere
    z, a = sigma_targets(th_i, th_j[None], mu_at, rho_at, 0.05)
    torch.testing.assert_close(z[0], (th_i + th_j) / 2)
    torch.testing.assert_close(a[0], torch.ones_like(th_i))
    th_j[rho_at] = th_i[rho_at] - 6.0  # the neighbour far surer (sigma about e^-6 x this node's)
    z, a = sigma_targets(th_i, th_j[None], mu_at, rho_at, 0.05)
    assert torch.allclose(z[0, mu_at], th_j[mu_at], atol=1e-3)  # the product of the Gaussians sits at its mean
    assert torch.allclose(a[0, mu_at], torch.full_like(a[0, mu_at], 1.95))  # and this node is pulled hard (clamped)
    z_back, a_back = sigma_targets(th_j, th_i[None], mu_at, rho_at, 0.05)  # seen from the surer node
    assert torch.allclose(z_back[0, mu_at], th_j[mu_at], atol=1e-3) and torch.allclose(a_back[0, mu_at], torch.full_like(a[0, mu_at], 0.05))
    others = torch.ones_like(th_i, dtype=torch.bool)
    others[mu_at] = False
    torch.testing.assert_close(z[0, others], ((th_i + th_j) / 2)[others])  # rho, the sine and output layers: DiNNO's
    assert (a[0, others] == 1).all()


def test_sigma_consensus_listens_less_to_an_outdated_state():
    model = network(bnn_settings(consensus="sigma"))
    mu_at, rho_at = sigma_pairs(model)
    th_i = torch.nn.utils.parameters_to_vector(model.parameters()).detach()
    th_j = th_i + 1.0
    th_j[rho_at] = th_i[rho_at]
    both = torch.stack([th_j, th_j])
    var = F.softplus(th_i[rho_at]).square()
    widen = torch.stack([torch.zeros_like(var), 3 * var])  # row 0 this round's, row 1 aged: widened by 3 sigma^2
    z, a = sigma_targets(th_i, both, mu_at, rho_at, 0.05, widen)
    fresh_z, fresh_a = sigma_targets(th_i, th_j[None], mu_at, rho_at, 0.05)
    torch.testing.assert_close(z[0], fresh_z[0])  # a fresh State beside an old one: as before
    torch.testing.assert_close(a[0], fresh_a[0])
    # the old one: its variance sigma^2 + 3 sigma^2, so s = 1/5 of the way, weight 2/5
    torch.testing.assert_close(a[1, mu_at], torch.full_like(var, 0.4))
    torch.testing.assert_close(z[1, mu_at], th_i[mu_at] + 0.2)
    others = torch.ones_like(th_i, dtype=torch.bool)
    others[mu_at] = False
    torch.testing.assert_close(a[1, others], torch.full_like(a[1, others], 0.4))  # without a posterior: the means' discount, 2/5
    z, a = sigma_targets(th_i, th_j[None], mu_at, rho_at, 0.05, 1e6 * var[None])
    assert (a[0, mu_at] < 1e-5).all()  # a State from long ago barely pulls: no floor for it


def test_sigma_keeps_outdated_states_and_widens_them_by_the_drift():
    s = bnn_settings(consensus="sigma", sigma_memory_rounds=10)
    n = node(s, 0, seed=0)
    assert n.keep_for == 10
    st = n.state()
    other = st + 0.01
    n.update(0, st, {1: other})
    moved = n.state()
    assert n.rule.drift is None  # one round seen: no move measured yet
    n.update(1, moved, {})  # the link is down: neighbour 1's State of round 0 still pulls
    assert 1 in n.known and n.rule.drift is not None
    step = torch.from_numpy(moved - st)
    torch.testing.assert_close(n.rule.drift[1], torch.square(step))
    # one move seen: all of it steady, so a State 3 rounds old has moved 3 steps: widened by 9 d^2
    torch.testing.assert_close(n.rule.widening(torch.tensor([3.0])), 9 * torch.square(step[n.rule.mu_at])[None])
    n.update(11, n.state(), {})  # its memory is over
    assert 1 not in n.known
    assert node(bnn_settings(), 0, seed=0).keep_for == 1


def test_sigma_memory_changes_nothing_when_every_state_comes():
    """Over perfect links every State is this round's: nothing to widen, every dual heard."""
    runs = [run_inproc(bnn_settings(consensus="sigma", sigma_memory_rounds=m), rounds=5)[1] for m in (0, 100)]
    for i in runs[0]:
        np.testing.assert_array_equal(runs[0][i], runs[1][i])


def test_sigma_memory_pulls_a_node_whose_links_are_down():
    """A round without States: with memory the node is still pulled towards its neighbours."""
    ends = []
    for memory in (0, 100):
        s = bnn_settings(consensus="sigma", sigma_memory_rounds=memory)
        n = node(s, 0, seed=1)
        st = n.state()
        other = node(s, 1, seed=2).update(0, st, {})
        st = n.update(0, st, {1: other})
        for k in range(1, 4):
            st = n.update(k, st, {})
        ends.append(np.abs(st - other).mean())
    assert ends[1] < ends[0]


def test_sigma_needs_a_bayesian_network_and_dinno():
    with pytest.raises(ValueError, match="needs model bnn"):
        LearnerSettings(consensus="sigma")
    with pytest.raises(ValueError, match="needs algorithm dinno"):
        LearnerSettings(consensus="ramen", algorithm="dsgd")
    with pytest.raises(ValueError, match="multiple of exchange_every"):
        LearnerSettings(rounds=25, exchange_every=10)
    with pytest.raises(ValueError, match="round_wait_s > 0"):
        LearnerSettings(graph="disk", data="online")


def test_dgvi_pools_the_neighbourhoods_gaussians_by_precision():
    from swarmmap.services.learner.consensus.dgvi import pooled, softplus_inverse

    model = network(bnn_settings(consensus="dgvi"))
    mu_at, rho_at = sigma_pairs(model)
    th_i = torch.nn.utils.parameters_to_vector(model.parameters()).detach().double()
    th_j = th_i + 1.0
    th_j[rho_at] = softplus_inverse(F.softplus(th_i[rho_at]) / 2)  # the neighbour: sigma halved, precision x4
    z = pooled(th_i, th_j[None], mu_at, rho_at)
    # omega_bar = (w + 4 w) / 2, mu_bar = (w mu_i + 4 w mu_j) / (5 w): 4/5 of the way to the surer one
    torch.testing.assert_close(z[mu_at], th_i[mu_at] + 0.8)
    torch.testing.assert_close(F.softplus(z[rho_at]), F.softplus(th_i[rho_at]) * (2 / 5) ** 0.5)
    others = torch.ones_like(th_i, dtype=torch.bool)
    others[mu_at] = False
    others[rho_at] = False
    torch.testing.assert_close(z[others], th_i[others] + 0.5)  # no posterior: the plain mean
    torch.testing.assert_close(pooled(th_i, th_i[None], mu_at, rho_at), th_i)  # equal Gaussians pool to themselves
    s = bnn_settings(consensus="dgvi")
    dn, _ = run_inproc(s, rounds=8)
    assert all(not n.duals or all(bool((d == 0).all()) for d in n.duals.values()) for n in dn)  # DGVI keeps no duals
    with pytest.raises(ValueError, match="consensus dgvi weighs by the posterior's sigma: it needs model bnn"):
        LearnerSettings(consensus="dgvi")


def test_ramen_weights_follow_ramens_scaling_and_reduce_to_dinno_for_equal_counts():
    th_i, th_j = torch.zeros(4), torch.tensor([[1.0, 1.0, 1.0, 1.0]])
    z, a = ramen_targets(th_i, torch.full((4,), 5.0), th_j, torch.full((1, 4), 5.0))
    torch.testing.assert_close(z[0], torch.full((4,), 0.5))
    torch.testing.assert_close(a[0], torch.ones(4))
    c_i, c_j = torch.tensor([0.0, 10.0, 10.0, 20.0]), torch.tensor([[10.0, 0.0, 10.0, 20.0]])
    z, a = ramen_targets(th_i, c_i, th_j, c_j)
    w_i = torch.tensor([1e-3, 0.5005, 0.5005, 1.0])  # counts 0..20 onto [rho / 1000, rho], in units of rho
    w_j = torch.tensor([0.5005, 1e-3, 0.5005, 1.0])
    torch.testing.assert_close(a[0], w_i)
    torch.testing.assert_close(z[0], (w_i * th_i + w_j * th_j[0]) / (w_i + w_j))
    assert z[0, 0] > 0.99 and z[0, 1] < 0.01  # towards the side that saw the parameter's data
    # counts all far from 0, as a dense network's are: weights stay positive, targets between the two
    z, a = ramen_targets(th_i, torch.tensor([500.0, 510, 520, 530]), th_j, torch.tensor([[530.0, 520, 510, 500]]))
    assert (a > 0).all() and (z >= 0).all() and (z <= 1).all()


def test_ramen_counts_travel_in_the_state_and_grow_with_the_steps():
    s = LearnerSettings(model_shape=[2, 16, 8, 1], consensus="ramen", rounds=4, primal_iterations=3, batch_size=256)
    nodes = [node(s, i, seed=i + 1) for i in range(2)]
    n = nodes[0].layout.param_count
    assert state_copies(s.algorithm, s.consensus) == 2
    th = {i: nodes[i].state().copy() for i in range(2)}
    assert th[0].shape == (2 * n,) and (th[0][n:] == 0).all()
    for k in range(2):
        th = {i: nodes[i].update(k, th[i], {1 - i: th[1 - i]}).copy() for i in range(2)}
    counts = th[0][n:]
    assert counts.max() == 6 and counts.min() >= 0  # 2 rounds x 3 steps, a count per step with a gradient


def test_rounds_between_exchanges_pull_towards_the_last_states_and_keep_the_duals():
    s = LearnerSettings(model_shape=[2, 16, 8, 1], rounds=4, primal_iterations=3, batch_size=256, rho_init=1.0,
                        exchange_every=2)
    a = node(s, 0, seed=1)
    lone = node(s, 0, seed=1)
    far = a.state().copy() + 0.5
    own = a.update(0, a.state().copy(), {1: far}).copy()
    duals = a.duals[1].clone()
    lone.update(0, lone.state().copy(), {})
    pulled = a.local_update(1, own).copy()
    alone = lone.local_update(1, own).copy()
    torch.testing.assert_close(a.duals[1], duals)
    # the stale neighbour still pulls: this node ends nearer to it than one trained alone from the same place
    assert np.linalg.norm(pulled - far) < np.linalg.norm(alone - far)


@pytest.mark.parametrize("consensus", ["dinno", "sigma"])
def test_the_two_duals_of_a_link_cancel(consensus):
    """Whatever the weights, node i's dual for j and node j's dual for i sum to zero after an
    exchange: an unbalanced pair would push the whole team off the data's optimum."""
    s = bnn_settings(consensus=consensus)
    a, b = (node(s, i, seed=i + 1) for i in range(2))
    th_a = a.state().copy()
    th_b = th_a + np.random.default_rng(0).normal(0, 0.05, th_a.shape).astype(np.float32)
    rho_b = [p.numel() for n, p in b.model.named_parameters()]  # make b far surer than a on some weights
    th_b[sum(rho_b[:3]) : sum(rho_b[:4])] -= 3.0  # seq.1.weight_rho
    a.update(0, th_a, {1: th_b})
    b.update(0, th_b, {0: th_a})
    torch.testing.assert_close(a.duals[1] + b.duals[0], torch.zeros_like(a.duals[1]), atol=1e-6, rtol=0)
    assert a.duals[1].abs().max() > 1e-4


def test_the_noise_contrastive_prior_makes_the_bnn_unsure_where_it_has_no_data():
    """A lone BNN sees only x < 2 of the 4 x 4 m box: with learner.unseen_weight its maps' std
    over x > 3 is several times what it is without (measured: 0.099 against 0.0096), while
    staying near 0 where it has data, and it still fits its data."""
    from swarmmap.shared.learning.bnn import predict_mean_std

    x, y = toy_data(0)
    seen = x[:, 0] < 2.0
    grid = np.stack(np.meshgrid(np.linspace(0.05, 3.95, 40), np.linspace(0.05, 3.95, 40)), -1).reshape(-1, 2)
    far, near = grid[:, 0] > 3.0, grid[:, 0] < 1.5
    spread, fits = {}, {}
    for weight in (0.0, 0.1):
        s = LearnerSettings(model="bnn", model_shape=[2, 32, 32, 32, 1], rounds=40, primal_iterations=5, batch_size=512,
                            lr_start=1e-2, lr_finish=1e-3, unseen_weight=weight, unseen_margin_m=0.4, unseen_points=128)
        n = node(s, 0, seed=1, data=(x[seen], y[seen]), bounds=BOUNDS)
        assert (n.coverage is not None) == (weight > 0)
        th = n.state()
        for k in range(40):
            th = n.update(k, th, {})
        _, std = predict_mean_std(n.model, grid.astype(np.float32), samples=30)
        spread[weight] = (float(std[far].mean()), float(std[near].mean()))
        fits[weight] = validation_bce(n.model, x[seen][:1000], y[seen][:1000])
    (far_with, near_with), (far_without, _) = spread[0.1], spread[0.0]
    assert far_with > 0.05 and far_with > 4 * far_without and near_with < 0.01, spread
    assert fits[0.1] < 0.3, fits


def test_the_noise_contrastive_prior_needs_the_maps_bounds():
    s = LearnerSettings(model="bnn", model_shape=[2, 8, 8, 1], unseen_weight=0.1)
    with pytest.raises(ValueError, match="bounds"):
        node(s, 0, seed=1)
