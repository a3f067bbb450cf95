"""DGVI's consensus (Paritosh, Atanasov & Martinez, arXiv 2309.02606): neighbours' Gaussians pooled.

Distributed Gaussian variational inference has each agent replace its diagonal Gaussian by the
geometric pool of its neighbourhood's (its own included): precision omega_bar = sum_j a_j omega_j
and mean mu_bar = omega_bar^-1 sum_j a_j omega_j mu_j (DGVI's ``model/slam_td.py``). Here it is a
consensus rule of DiNNO's primal loop: with a_j = 1 / (n + 1) over the node and the n neighbours
whose States it holds, every link's target is that pool: mu_bar for each Bayesian mean, the rho
of sigma_bar = omega_bar^-1/2 for its rho, the plain mean for every other parameter (the sine
layer, the output layer); weight 1; no dual (DGVI has none), so each link adds rho ||theta - z||^2.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from swarmmap.services.learner.consensus.base import PlainLoss
from swarmmap.services.learner.consensus.sigma import sigma_pairs


def softplus_inverse(x: torch.Tensor) -> torch.Tensor:
    """rho with softplus(rho) = x (x > 0), stable for small and large x."""
    return x + torch.log(-torch.expm1(-x))


def pooled(th_i: torch.Tensor, thj: torch.Tensor, mu_at: torch.Tensor, rho_at: torch.Tensor) -> torch.Tensor:
    """The geometric pool of the Gaussians in ``th_i`` and the rows of ``thj``, equal weights."""
    everyone = torch.cat([th_i[None], thj])
    z = everyone.mean(0)
    precision = F.softplus(everyone[:, rho_at]).square().reciprocal()  # omega_j of every Bayesian weight
    omega = precision.mean(0)
    z[mu_at] = (precision * everyone[:, mu_at]).mean(0) / omega
    z[rho_at] = softplus_inverse(omega.rsqrt())
    return z


class DgviRule(PlainLoss):
    """Target: the neighbourhood's pooled Gaussian for every link; weight 1; no dual."""

    name = "dgvi"

    def __init__(self, model: torch.nn.Module):
        self.mu_at, self.rho_at = sigma_pairs(model)

    def targets(self, ages, th_i, thj, extras):
        z = pooled(th_i, thj, self.mu_at, self.rho_at)
        return z.expand_as(thj), None

    def dual_step(self, rho: float, th_i: torch.Tensor, th_j: torch.Tensor, z, a) -> torch.Tensor:
        return torch.zeros_like(th_i)
