"""Robust consensus: a lying member is an outlier of the round's States, its pull and dual are
bounded, sigma does not take a neighbour's word for its certainty, and every named attack is what
it says it is."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmmap.services.learner.attacks import Liar, output_layer
from swarmmap.services.learner.consensus.sigma import sigma_pairs, sigma_targets
from swarmmap.services.learner.robust import PullBound, RoundScreen
from swarmmap.services.learner.screening import StateScreen
from swarmmap.shared.learning.layout import StateLayout
from swarmmap.shared.learning.networks import build_model

BOUNDS = (0.0, 0.0, 4.0, 4.0)


def layout(kind="fourier", shape=(2, 32, 16, 16, 1), copies=1):
    model = build_model(list(shape), 5.0, BOUNDS, 0, kind)
    return model, StateLayout.of(model, copies)


def team(own: np.ndarray, n: int, spread: float, seed: int = 0) -> dict[int, np.ndarray]:
    """``n`` honest neighbours: ``own`` moved by noise of ``spread`` of its scale per value."""
    rng = np.random.default_rng(seed)
    scale = np.abs(own).mean()
    return {j: (own + spread * scale * rng.standard_normal(own.size)).astype(np.float32) for j in range(1, n + 1)}


@pytest.mark.parametrize("attack", ["ratchet", "signflip", "scale"])
def test_a_lie_is_an_outlier_among_honest_states_and_the_honest_pass(attack):
    model, lay = layout()
    own = torch.nn.utils.parameters_to_vector(model.parameters()).detach().numpy().copy()
    peers = team(own, 5, 0.02)
    peers[6] = Liar(attack, lay, 0).lie(peers[5])
    refused = RoundScreen(lay)(own, peers)
    assert set(refused) == {6}, refused
    assert "the round's spread" in refused[6]


def test_a_bnns_false_certainty_is_refused_though_its_norm_barely_moves():
    model, lay = layout("bnn")
    own = torch.nn.utils.parameters_to_vector(model.parameters()).detach().numpy().copy()
    peers = team(own, 4, 0.01)
    peers[9] = Liar("sigma", lay, 0).lie(peers[1])
    assert np.linalg.norm(peers[9] - own) < 0.5 * np.linalg.norm(own)  # what the plain norm check let through
    assert set(RoundScreen(lay)(own, peers)) == {9}
    # The means moved by 0.45 of the whole norm, rho untouched: within the plain norm check's 0.5,
    # many times the means' own norm (rho, about -5 each, makes up almost all of the norm).
    rho = np.concatenate([np.arange(at, at + n) for name, at, n in lay.tensors if name.endswith("_rho")])
    mu = np.setdiff1d(np.arange(lay.param_count), rho)
    direction = np.random.default_rng(1).standard_normal(mu.size)
    means_only = own.copy()
    means_only[mu] += (0.45 * np.linalg.norm(own) * direction / np.linalg.norm(direction)).astype(np.float32)
    assert np.linalg.norm(means_only - own) < 0.5 * np.linalg.norm(own)
    assert np.linalg.norm(means_only[mu] - own[mu]) > 10 * np.linalg.norm(own[mu])
    assert StateScreen(lay, 0.5)(means_only, own).startswith("means: parameters")


def test_identical_states_of_round_0_pass_and_anything_else_is_refused():
    model, lay = layout()
    own = torch.nn.utils.parameters_to_vector(model.parameters()).detach().numpy().copy()
    peers = {j: own.copy() for j in range(1, 5)}
    peers[5] = Liar("noise", lay, 0).lie(own)
    assert set(RoundScreen(lay)(own, peers)) == {5}


def test_with_fewer_than_three_neighbours_the_screen_refuses_no_honest_state():
    """A node left with two neighbours (one banned, a ring) cannot tell a round's honest spread:
    a spread of earlier rounds (identical States at round 0, then growing) would refuse honest
    neighbours that have moved on, so only the per-State checks judge."""
    model, lay = layout()
    own = torch.nn.utils.parameters_to_vector(model.parameters()).detach().numpy().copy()
    screen = RoundScreen(lay)
    assert screen(own, {j: own.copy() for j in range(1, 5)}) == {}  # round 0: the team is identical
    assert screen(own, team(own, 2, 0.05, seed=1)) == {}  # two neighbours that have since moved apart
    few = team(own, 4, 0.02, seed=2)
    few[7] = Liar("scale", lay, 0).lie(own)
    assert set(screen(own, few)) == {7}  # with enough neighbours the liar is an outlier


def test_each_links_pull_and_dual_are_clipped_to_a_multiple_of_the_median():
    model, lay = layout()
    th_i = torch.nn.utils.parameters_to_vector(model.parameters()).detach()
    rows = th_i + 0.01 * torch.randn(5, th_i.numel(), generator=torch.Generator().manual_seed(0))
    rows[4] = th_i + 10 * (rows[4] - th_i)
    bound = PullBound(lay, 3.0)
    clipped = bound.rows(th_i, rows)
    torch.testing.assert_close(clipped[:4], rows[:4])  # the honest ones are left as they are
    assert torch.linalg.norm(clipped[4] - th_i) < 3.5 * torch.linalg.norm(rows[0] - th_i)
    duals = {j: (rows[j] - th_i).clone() for j in range(5)}
    bound.duals(duals)
    assert torch.linalg.norm(duals[4]) < 3.5 * torch.linalg.norm(duals[0]) and torch.equal(duals[1], rows[1] - th_i)
    assert bound.rows(th_i, rows[:2]) is not None and torch.equal(bound.rows(th_i, rows[:2]), rows[:2])  # too few to judge


def test_sigma_does_not_take_a_neighbours_word_for_its_certainty():
    model, _ = layout("bnn")
    mu_at, rho_at = sigma_pairs(model)
    th_i = torch.nn.utils.parameters_to_vector(model.parameters()).detach()
    th_j = th_i.clone()
    th_j[mu_at] += 1.0
    th_j[rho_at] -= 2.0  # claims sigma about e^-2 x this node's
    z, a = sigma_targets(th_i, th_j[None], mu_at, rho_at, 0.05)
    assert a[0, mu_at].max() > 1.9  # as sure as it says: pulled almost all the way
    z, a = sigma_targets(th_i, th_j[None], mu_at, rho_at, 0.05, max_weight=1.5)
    assert a[0, mu_at].max() <= 1.5 + 1e-6 and (z[0, mu_at] - th_i[mu_at]).max() <= 0.75 + 1e-6
    _, back = sigma_targets(th_j, th_i[None], mu_at, rho_at, 0.05, max_weight=1.5)  # the other end of the link
    torch.testing.assert_close(a[0, mu_at] + back[0, mu_at], torch.full_like(a[0, mu_at], 2.0))  # duals still cancel


def test_each_attack_is_what_it_says():
    model, lay = layout("bnn", copies=1)
    v = torch.nn.utils.parameters_to_vector(model.parameters()).detach().numpy().copy()
    norm = np.linalg.norm(v)
    out = output_layer(lay)
    np.testing.assert_array_equal(Liar("signflip", lay, 0).lie(v)[out], -v[out])
    np.testing.assert_allclose(Liar("scale", lay, 0).lie(v), 1.45 * v, rtol=1e-6)
    assert np.linalg.norm(Liar("ratchet", lay, 0).lie(v) - v) == pytest.approx(0.45 * norm, rel=1e-3)
    assert np.linalg.norm(Liar("noise", lay, 0).lie(v) - v) == pytest.approx(0.05 * norm, rel=0.05)
    lie = Liar("sigma", lay, 0).lie(v)
    rho = np.concatenate([np.arange(at, at + n) for name, at, n in lay.tensors if name.endswith("_rho")])
    np.testing.assert_allclose(lie[rho], v[rho] - 2, rtol=1e-6)
    ratchet = Liar("ratchet", lay, 0)
    assert not np.allclose(ratchet.lie(v), ratchet.lie(v))  # a new direction every round


def test_a_state_scaled_within_the_distance_limit_is_refused_by_its_norm():
    """1.45 x a node's own parameters lies 0.45 of their norm away (under the 0.5 limit) but its
    norm is 1.45 times theirs: refused; a neighbour back from learning apart (the loose check)
    is not judged by its norm."""
    from swarmmap.services.learner.screening import StateScreen
    from swarmmap.shared.learning.layout import StateLayout

    own = np.random.default_rng(0).standard_normal(1000).astype(np.float32)
    screen = StateScreen(StateLayout(1000, tensors=(("0.weight", 0, 1000),)), 0.5)
    assert screen(own * 1.45, own).startswith("parameters of 1.45 x the own parameters' norm")
    assert screen(own * 1.1 + 0.01, own) is None
    assert screen.loose(own * 1.8, own) is None
