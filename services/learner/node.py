"""What Algorithm 1 and the service know of a learning rule (:class:`Node`), and what every rule
builds on (:class:`LocalNode`: a robot's model, its local data and the loss on a batch of it).

Rules: DiNNO (:mod:`~swarmmap.services.learner.dinno`), DiNNO's DSGD and DSGT baselines
(:mod:`~swarmmap.services.learner.baselines`); :data:`~swarmmap.services.learner.registry.NODES`
picks one by ``learner.algorithm``. A node's State is one float32 vector laid out as
:class:`~swarmmap.shared.learning.layout.StateLayout` says.

The loss is BCE on a random batch, plus ``kl_weight`` x the KL to the prior for a Bayesian
network (the paper's equation 7), plus, with ``unseen_weight`` > 0, the noise-contrastive prior
on points away from every robot's data known to this node (:class:`~swarmmap.shared.world.unseen.Coverage`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F

from swarmmap.services.learner.optim import make_optimizer
from swarmmap.services.learner.settings import TrainingSettings
from swarmmap.services.learner.transport import plain_vector
from swarmmap.shared.learning.bnn import BayesNet, function_prior_kl, sampled_logits
from swarmmap.shared.learning.layout import StateLayout
from swarmmap.shared.learning.models import StochasticNet, flatten_into
from swarmmap.shared.world.unseen import Coverage


class Node(Protocol):
    """A learning rule at one robot: the seam between the exchange and the algorithm."""

    model: torch.nn.Module
    layout: StateLayout
    coverage: Coverage | None

    def update(self, k: int, state: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """NODEUPDATE of training round ``k`` given the neighbours' States of that round; the new State."""

    def local_update(self, k: int, state: np.ndarray) -> np.ndarray:
        """A training round between exchanges (``exchange_every`` > 1): no new States; the new State."""

    def forget(self, j: int) -> None:
        """Neighbour ``j`` went silent: stop using its last State."""

    def state(self) -> np.ndarray:
        """The State this node sends now."""

    def rejoin(self, own: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """The State to go on from after catching up with the team."""

    def set_data(self, points: np.ndarray, labels: np.ndarray) -> None:
        """Replace the local data (online training's sliding window)."""

    def checkpoint(self) -> dict:
        """Everything besides the State that the next rounds depend on."""

    def restore(self, doc: dict) -> None:
        """Take back what :meth:`checkpoint` returned."""


def lr_schedule(kind: str, start: float, finish: float, rounds: int) -> np.ndarray:
    """DiNNO's ``primal_lr``: constant, linear or log-spaced from ``start`` to ``finish``."""
    if kind == "constant":
        return np.full(rounds, start)
    if kind == "linear":
        return np.linspace(start, finish, rounds)
    if kind == "log":
        return np.logspace(math.log10(start), math.log10(finish), rounds)
    raise ValueError(f"unknown lr_schedule {kind!r}; allowed: constant, linear, log")


def warm_up(optimizer: str) -> None:
    """Load now what a node's first optimizer step would load (torch's autograd and kernels). Done
    before Algorithm 1 starts (while the robots drive), it does not slow round 0. Draws no random
    numbers and keeps nothing."""
    p = torch.zeros(1, requires_grad=True)
    opt = make_optimizer(optimizer, [p], 1e-3)
    (2 * p).sum().backward()
    opt.step()


@dataclass(frozen=True)
class NodeInputs:
    """What every node is made of: its network, its data, its loss's settings, its seed (the
    batch generator's; a stochastic network's weight draws or dropout masks come from a generator
    of their own), its State's layout, where its prior doubts (None: nowhere) and ``new_state(n)``,
    the vector each State is written into (the transport's payload, where it has one)."""

    model: torch.nn.Module
    points: np.ndarray
    labels: np.ndarray
    training: TrainingSettings
    seed: int
    layout: StateLayout
    coverage: Coverage | None = None
    new_state: Callable[[int], np.ndarray] = plain_vector


class LocalNode:
    """A node's model, its local data and the loss on a random batch of it."""

    def __init__(self, inputs: NodeInputs):
        model = inputs.model
        self.model, self.layout, self.coverage, self.new_state = model, inputs.layout, inputs.coverage, inputs.new_state
        self.device = next(model.parameters()).device
        self.points = torch.from_numpy(np.ascontiguousarray(inputs.points)).to(self.device)
        self.labels = torch.from_numpy(np.ascontiguousarray(inputs.labels)).to(self.device)
        self.t = t = inputs.training
        self.lrs = lr_schedule(t.lr_schedule, t.lr_start, t.lr_finish, t.rounds)
        self.gen = torch.Generator(device="cpu").manual_seed(inputs.seed)
        self.bayesian = isinstance(model, BayesNet)
        self.noise: torch.Generator | None = None
        if isinstance(model, StochasticNet):  # weight draws or dropout masks: the node's own stream
            self.noise = torch.Generator(device=self.device).manual_seed(inputs.seed + 7_000_003)
            model.use_generator(self.noise)

    def lr(self, k: int) -> float:
        """The learning rate of training round ``k``."""
        return float(self.lrs[min(k, len(self.lrs) - 1)])

    def checkpoint(self) -> dict:
        """Everything besides the parameters that the next rounds depend on (RNG states too, so
        a resumed run repeats the uninterrupted one)."""
        doc = {"gen": self.gen.get_state(), "noise": None if self.noise is None else self.noise.get_state()}
        if self.coverage is not None:
            doc["coverage"] = torch.from_numpy(self.coverage.others.copy())  # (a tensor: torch.load reads it with weights_only)
        return doc

    def restore(self, doc: dict) -> None:
        self.gen.set_state(doc["gen"])
        if self.noise is not None and doc.get("noise") is not None:
            self.noise.set_state(doc["noise"])
        if self.coverage is not None and doc.get("coverage") is not None and tuple(doc["coverage"].shape) == self.coverage.shape:
            self.coverage.merge_cells(np.asarray(doc["coverage"]))

    def set_data(self, points: np.ndarray, labels: np.ndarray) -> None:
        """Replace the local data (online training's sliding window)."""
        self.points = torch.from_numpy(np.ascontiguousarray(points)).to(self.device)
        self.labels = torch.from_numpy(np.ascontiguousarray(labels)).to(self.device)
        if self.coverage is not None:
            self.coverage.set_points(points)

    def extra(self) -> list[torch.Tensor]:
        """What the State carries after the parameters (none here)."""
        return []

    def state(self) -> np.ndarray:
        """The flat parameters (and :meth:`extra`), written once into a vector from ``new_state``."""
        return flatten_into([*self.model.parameters(), *self.extra()], self.new_state(self.layout.size))

    def forget(self, j: int) -> None:
        """Nothing of a neighbour is kept here."""

    def rejoin(self, own: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """The state a node that was away starts from when it catches up with its team: its own,
        from its checkpoint (a few rounds old while its neighbours wait ``rejoin_wait_s`` for it;
        consensus pulls it in). Measured against the mean of its own and its neighbours' States,
        which wipes out what it alone had learnt of its part of the plan (tests/e2e/test_failures.py)."""
        return own

    def begin_round(self, k: int) -> None:
        """Take in what the team's States of rounds before ``k`` said they cover."""
        if self.coverage is not None:
            self.coverage.advance(k)

    def batch_loss(self) -> torch.Tensor:
        """BCE on a random batch, plus kl_weight x KL to the prior for a Bayesian network."""
        bce, kl = self.batch_terms()
        return bce if kl is None else bce + kl

    def batch_terms(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The batch loss's two terms: BCE on a random batch, and kl_weight x KL to the prior
        (None for a deterministic network)."""
        idx = torch.randint(0, len(self.points), (min(self.t.batch_size, len(self.points)),), generator=self.gen)
        idx = idx.to(self.device)
        bce = F.binary_cross_entropy_with_logits(self.model.logits(self.points[idx]), self.labels[idx])
        kl = self.t.kl_weight * self.model.kl() if self.bayesian and self.t.kl_weight > 0 else None
        away = self.unseen_term()
        return bce, away if kl is None else kl if away is None else kl + away

    def unseen_term(self) -> torch.Tensor | None:
        """``unseen_weight`` x the noise-contrastive prior's KL at ``unseen_points`` points drawn
        where no robot known to this node has data (None when off or nothing is uncovered)."""
        if self.coverage is None:
            return None
        xy = self.coverage.sample(self.t.unseen_points, self.gen, self.device)
        if xy is None:
            return None
        logits = sampled_logits(self.model, xy, self.t.unseen_draws, self.noise)
        return self.t.unseen_weight * function_prior_kl(logits, self.t.unseen_prior_std)

    def gradient(self) -> torch.Tensor:
        """The flat gradient of the batch loss at the current parameters."""
        self.model.zero_grad()
        self.batch_loss().backward()
        return torch.cat([p.grad.reshape(-1) for p in self.model.parameters()]).detach().clone()


def coverage_for(model: torch.nn.Module, training: TrainingSettings, margin: float,
                 bounds: tuple[float, float, float, float] | None, points: np.ndarray) -> Coverage | None:
    """Where a Bayesian network's noise-contrastive prior samples its points (None when it is off)."""
    if not isinstance(model, BayesNet) or training.unseen_weight <= 0:
        return None
    if bounds is None:
        raise ValueError("learner.unseen_weight needs the map's bounds (where the unseen space lies)")
    return Coverage(bounds, margin, points)
