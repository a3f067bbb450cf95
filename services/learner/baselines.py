"""DiNNO's decentralised baselines: DSGD and DSGT, with Metropolis mixing weights.

Both mix the States of the round's neighbours (``weights``, :func:`~swarmmap.shared.learning.graphs.metropolis_weights`;
an absent neighbour's weight stays with the node) and take one gradient step of size ``lr(k)``.
Between exchanges (``learner.exchange_every`` > 1) a round has nobody to mix with: DSGD takes a
plain local gradient step, DSGT a tracked step with the identity for mixing (theta <- theta -
alpha y, y <- y + g(theta) - g_old), as local-update variants of both do.
"""

from __future__ import annotations

import numpy as np
import torch

from swarmmap.services.learner.node import LocalNode, NodeInputs
from swarmmap.services.learner.robust import PullBound
from swarmmap.shared.learning.models import set_flat


def self_weight(weights: dict[int, float], node: int, peers: dict[int, np.ndarray]) -> float:
    """A node's mixing weight for a round: its own, plus that of every neighbour absent from it."""
    return weights[node] + sum(w for j, w in weights.items() if j != node and j not in peers)


def bounded(peers: dict[int, np.ndarray], own: np.ndarray, bound: PullBound | None, device) -> dict[int, torch.Tensor]:
    """The neighbours' States as tensors, each one's difference from ``own`` clipped by ``bound`` (robust consensus)."""
    rows = {j: torch.as_tensor(v, device=device) for j, v in peers.items()}
    if bound is None or not rows:
        return rows
    clipped = bound.rows(torch.as_tensor(own, device=device), torch.stack(list(rows.values())))
    return dict(zip(rows, clipped))


class DsgdNode(LocalNode):
    """DiNNO's DSGD: mix with the neighbours by Metropolis weights, then one gradient step at the
    mixed parameters. (DiNNO's single-process loop mixes in place, so later nodes see earlier
    nodes' new values; here every node mixes round-k values, as independent processes must.)"""

    def __init__(self, inputs: NodeInputs, weights: dict[int, float], node: int, bound: PullBound | None = None):
        super().__init__(inputs)
        self.weights, self.node, self.bound = weights, node, bound

    def update(self, k: int, theta_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        self.begin_round(k)
        own = self_weight(self.weights, self.node, peers)  # an absent neighbour's weight stays home
        mixed = own * torch.as_tensor(theta_i, device=self.device)
        for j, th in bounded(peers, theta_i, self.bound, self.device).items():
            mixed = mixed + self.weights[j] * th
        return self._step(k, mixed)

    def local_update(self, k: int, theta_i: np.ndarray) -> np.ndarray:
        """A round between exchanges: one gradient step from the node's own parameters."""
        self.begin_round(k)
        return self._step(k, torch.as_tensor(theta_i, device=self.device))

    def _step(self, k: int, theta: torch.Tensor) -> np.ndarray:
        set_flat(self.model, theta)
        g = self.gradient()
        set_flat(self.model, theta - self.lr(k) * g)
        return self.state()


class DsgtNode(LocalNode):
    """DiNNO's DSGT (gradient tracking): the State carries [theta, y]; per round
    theta <- W_ii theta - alpha y_i + sum_j W_ij theta_j, then y <- W_ii y_i + sum_j W_ij y_j
    + g(theta) - g_old, with y and g_old starting at the gradient at theta_0."""

    def __init__(self, inputs: NodeInputs, weights: dict[int, float], node: int, bound: PullBound | None = None):
        super().__init__(inputs)
        self.weights, self.node, self.bound = weights, node, bound
        self.n = self.layout.param_count
        self.g_old = self.gradient()
        self.y = self.g_old.clone()

    def checkpoint(self) -> dict:
        return {**super().checkpoint(), "y": self.y.cpu(), "g_old": self.g_old.cpu()}

    def restore(self, doc: dict) -> None:
        super().restore(doc)
        self.y, self.g_old = doc["y"].to(self.device), doc["g_old"].to(self.device)

    def extra(self) -> list[torch.Tensor]:
        return [self.y]  # the tracker travels after the parameters

    def update(self, k: int, state_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        self.begin_round(k)
        n, w = self.n, self.weights
        own = torch.as_tensor(state_i, device=self.device)
        alpha = self.lr(k)
        w_own = self_weight(w, self.node, peers)
        theta = w_own * own[:n] - alpha * own[n:]
        y = w_own * own[n:]
        for j, other in bounded(peers, state_i, self.bound, self.device).items():
            theta = theta + w[j] * other[:n]
            y = y + w[j] * other[n:]
        return self._track(theta, y)

    def local_update(self, k: int, state_i: np.ndarray) -> np.ndarray:
        """A round between exchanges: the tracked step with nobody to mix with."""
        self.begin_round(k)
        own = torch.as_tensor(state_i, device=self.device)
        return self._track(own[: self.n] - self.lr(k) * own[self.n :], own[self.n :])

    def _track(self, theta: torch.Tensor, y: torch.Tensor) -> np.ndarray:
        set_flat(self.model, theta)
        g = self.gradient()
        self.y = y + g - self.g_old
        self.g_old = g
        return self.state()
