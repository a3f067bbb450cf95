"""DiNNO's consensus (Yu, Vincent & Schwager 2022): every parameter pulled alike towards the midpoint."""

from __future__ import annotations

import torch

from swarmmap.services.learner.consensus.base import PlainLoss


class DinnoRule(PlainLoss):
    """Target z_ij = (theta_i + theta_j) / 2, weight 1; dual step rho (theta_i - theta_j)."""

    name = "dinno"

    def targets(self, ages, th_i, thj, extras):
        return (thj + th_i) / 2, None

    def dual_step(self, rho: float, th_i: torch.Tensor, th_j: torch.Tensor, z, a) -> torch.Tensor:
        return rho * (th_i - th_j)
