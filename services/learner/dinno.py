"""DiNNO's node update (Yu, Vincent & Schwager 2022), free of any transport.

Per round k, for node i with neighbour parameters theta_j (as DiNNO's ``optimizers/dinno.py``):
rho <- rho * growth; duals p_i += rho * sum_j (theta_i - theta_j); targets
theta_reg_j = (theta_i + theta_j) / 2; then ``primal_iterations`` optimizer steps on
``BCE(batch) + <theta, p_i> + rho * sum_j ||theta - theta_reg_j||^2`` with a fresh optimizer
whose learning rate follows the schedule. A node without neighbours takes plain BCE steps.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from swarmmap.shared.config import LearnerSettings
from swarmmap.shared.models import FourierNet, get_flat, set_flat


def lr_schedule(kind: str, start: float, finish: float, rounds: int) -> np.ndarray:
    """DiNNO's ``primal_lr``: constant, linear or log-spaced from ``start`` to ``finish``."""
    if kind == "constant":
        return np.full(rounds, start)
    if kind == "linear":
        return np.linspace(start, finish, rounds)
    if kind == "log":
        return np.logspace(math.log10(start), math.log10(finish), rounds)
    raise ValueError(f"unknown lr_schedule {kind!r}; allowed: constant, linear, log")


def make_optimizer(kind: str, params, lr: float) -> torch.optim.Optimizer:
    if kind == "adam":
        return torch.optim.Adam(params, lr=lr)
    if kind == "adamw":
        return torch.optim.AdamW(params, lr=lr)
    if kind == "sgd":
        return torch.optim.SGD(params, lr=lr)
    raise ValueError(f"unknown optimizer {kind!r}; allowed: adam, adamw, sgd")


class DinnoNode:
    """One node's model, data, duals and rho; :meth:`update` is Algorithm 1's NODEUPDATE."""

    def __init__(self, model: FourierNet, points: torch.Tensor, labels: torch.Tensor,
                 settings: LearnerSettings, seed: int):
        self.model = model
        self.device = next(model.parameters()).device
        self.points = points.to(self.device)
        self.labels = labels.to(self.device)
        self.s = settings
        self.rho = settings.rho_init
        self.duals = torch.zeros_like(get_flat(model))
        self.lrs = lr_schedule(settings.lr_schedule, settings.lr_start, settings.lr_finish, settings.rounds)
        self.gen = torch.Generator(device="cpu").manual_seed(seed)

    def state(self) -> np.ndarray:
        return get_flat(self.model).cpu().numpy().astype(np.float32)

    def batch_loss(self) -> torch.Tensor:
        idx = torch.randint(0, len(self.points), (min(self.s.batch_size, len(self.points)),), generator=self.gen)
        idx = idx.to(self.device)
        return F.binary_cross_entropy_with_logits(self.model.logits(self.points[idx]), self.labels[idx])

    def update(self, k: int, theta_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """One DiNNO round for this node given neighbours' parameters of round ``k``."""
        th_i = torch.as_tensor(theta_i, device=self.device)
        set_flat(self.model, th_i)
        self.rho *= self.s.rho_growth
        th_reg = None
        if peers:
            thj = torch.stack([torch.as_tensor(p, device=self.device) for p in peers.values()])
            self.duals += self.rho * torch.sum(th_i - thj, dim=0)
            th_reg = (thj + th_i) / 2
        opt = make_optimizer(self.s.optimizer, self.model.parameters(), float(self.lrs[min(k, len(self.lrs) - 1)]))
        for _ in range(self.s.primal_iterations):
            opt.zero_grad()
            loss = self.batch_loss()
            if th_reg is not None:
                th = torch.nn.utils.parameters_to_vector(self.model.parameters())
                reg = torch.sum(torch.square(th[None, :] - th_reg))
                loss = loss + torch.dot(th, self.duals) + self.rho * reg
            loss.backward()
            opt.step()
        return self.state()


@torch.no_grad()
def validation_bce(model: FourierNet, points: torch.Tensor, labels: torch.Tensor, batch: int = 65536) -> float:
    """Mean binary cross-entropy of ``model`` over a validation set."""
    total = 0.0
    for s in range(0, len(points), batch):
        logits = model.logits(points[s : s + batch])
        total += float(F.binary_cross_entropy_with_logits(logits, labels[s : s + batch], reduction="sum"))
    return total / max(len(points), 1)


def consensus_error(theta_i: np.ndarray, peers: dict[int, np.ndarray]) -> float:
    """DiNNO's consensus metric for one node: mean distance between its unit-normalised
    parameter vector and its neighbours' (0 with no neighbours)."""
    if not peers:
        return 0.0
    a = theta_i / max(np.linalg.norm(theta_i), 1e-12)
    return float(np.mean([np.linalg.norm(a - p / max(np.linalg.norm(p), 1e-12)) for p in peers.values()]))
