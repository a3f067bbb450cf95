"""Where a robot has no data (its coverage grid, shared between teammates) and the
noise-contrastive prior that teaches its Bayesian network to be unsure there."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmmap.shared.learning.bnn import BayesNet, function_prior_kl, sampled_logits
from swarmmap.shared.world.unseen import Coverage

BOUNDS = (0.0, 0.0, 6.0, 4.0)


def strip(x0: float, x1: float, n: int = 4000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(x0, x1, n), rng.uniform(0, 4, n)])


def test_samples_lie_only_away_from_the_data():
    data = strip(0, 2)
    cov = Coverage(BOUNDS, 0.5, data)
    xy = cov.sample(2000, torch.Generator().manual_seed(0)).numpy()
    assert xy[:, 0].min() > 2.0 + 0.5 - cov.cell * np.sqrt(2)  # never within the margin (up to a cell)
    assert xy[:, 0].max() <= 6.0 and xy[:, 1].min() >= 0 and xy[:, 1].max() <= 4.0
    assert abs(xy[:, 0].mean() - (2.5 + 6.0) / 2) < 0.2  # uniform over what is left
    assert 0.55 < cov.uncovered_fraction() < 0.62
    assert Coverage(BOUNDS, 0.5, strip(0, 6)).sample(10, torch.Generator()) is None  # all covered: no prior


def test_a_teammates_coverage_is_merged_and_passed_on():
    a, b, c = Coverage(BOUNDS, 0.5, strip(0, 2)), Coverage(BOUNDS, 0.5, strip(4, 6)), Coverage(BOUNDS, 0.5, np.zeros((0, 2)))
    assert c.uncovered_fraction() == 1.0
    b.offer(0, a.packed())
    assert b.advance(1)
    b.offer(1, a.packed())
    assert not b.advance(2)  # new cells once, then nothing new
    c.offer(2, b.packed())
    assert c.advance(3)  # b passes a's cells on
    np.testing.assert_array_equal(c.covered(), a.own | b.own)
    xy = c.sample(1000, torch.Generator().manual_seed(1)).numpy()
    assert ((xy[:, 0] > 2.2) & (xy[:, 0] < 3.8)).all()  # only the gap nobody saw
    with pytest.raises(ValueError, match="expected"):
        a.offer(0, np.zeros(3, np.uint8))  # another map's grid


def test_the_prior_term_is_small_for_unsure_draws_and_large_for_sure_ones():
    g = torch.Generator().manual_seed(0)
    unsure = 3.0 * torch.randn((256, 500), generator=g)
    sure = 4.0 + 0.01 * torch.randn((256, 500), generator=g)
    assert function_prior_kl(unsure, 3.0) < 0.01
    assert function_prior_kl(sure, 3.0) > 4.0


def test_sampled_logits_are_draws_of_the_network_with_gradients():
    net = BayesNet([2, 16, 8, 8, 1], 2.0, BOUNDS, rho_init=-2.0)
    xy = torch.rand((32, 2)) * 4
    z = sampled_logits(net, xy, 5, torch.Generator().manual_seed(3))
    assert z.shape == (5, 32) and z.std(0).min() > 0
    z.sum().backward()
    assert net.seq[1].weight_rho.grad is not None and net.seq[1].weight_rho.grad.abs().sum() > 0


def test_offered_coverage_counts_from_the_round_after_its_state():
    """Coverage that came with a State of round r is taken in when the node starts round r + 1,
    whenever the State arrived, so that runs repeat over any transport."""
    a, b = Coverage(BOUNDS, 0.5, strip(0, 2)), Coverage(BOUNDS, 0.5, np.zeros((0, 2)))
    b.offer(3, a.packed())
    assert not b.advance(3) and not b.covered().any()
    assert b.advance(4) and b.pending == {}
    np.testing.assert_array_equal(b.covered(), a.own)
    with pytest.raises(ValueError, match="expected"):
        b.offer(5, np.zeros(2, np.uint8))


def test_a_flood_of_rounds_holds_at_most_a_bounded_number_of_grids():
    from swarmmap.shared.world.unseen import MAX_PENDING_ROUNDS

    a, b = Coverage(BOUNDS, 0.5, strip(0, 2)), Coverage(BOUNDS, 0.5, np.zeros((0, 2)))
    for r in range(1000):
        b.offer(10**6 - r, a.packed())
    assert len(b.pending) == MAX_PENDING_ROUNDS
    assert not b.advance(5)  # rounds from far ahead wait until the node gets there
    b.offer(7, a.packed())  # an honest State's coverage is not held back behind them
    assert b.advance(8)
