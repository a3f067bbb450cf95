"""How the consensus term treats a network's parameters: the paper's Figure 7 strategies.

:class:`UniformL2` treats every parameter alike (one optimizer; DiNNO's term, the only one for a
deterministic network). For a Bayesian network, :class:`SeparateL2` and :class:`Algorithm2`
give the mu-parameters and the rho-parameters an optimizer each and weigh their penalties by
W_mu = w_mu x rho and W_rho = w_rho x rho. :class:`Algorithm2` is the paper's Algorithm 2
(``separate-kl``): L2 for mu, and for rho the KL divergence (equation 6) between
N(0, softplus(rho_i)^2) and N(0, softplus(rho_reg_j)^2) summed over parameters and neighbours:
the two Gaussians share their mean, so the term pulls only the spreads together, on the scale
of the spreads rather than of raw rho values. Both losses are back-propagated before either
optimizer steps, so rho also learns from the prediction loss.

Each penalty takes the node's parameters ``th``, one target row per neighbour ``th_reg`` and
the consensus rule's weights ``a`` (same shape; None: 1 everywhere).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from swarmmap.services.learner.settings import RegularizationSettings
from swarmmap.shared.learning.bnn import BayesNet, gaussian_kl, is_rho


def l2(x: torch.Tensor, target: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
    """sum_j sum_p w_jp (x_p - target_jp)^2."""
    sq = torch.square(x[None, :] - target)
    return torch.sum(sq if w is None else w * sq)


class UniformL2:
    """Every parameter alike: rho x sum_j a_ij (theta - z_ij)^2."""

    name = "uniform-l2"

    def groups(self, model: torch.nn.Module) -> list[list[torch.nn.Parameter]]:
        """The parameter groups that get an optimizer each."""
        return [list(model.parameters())]

    def penalty(self, rho: float, th: torch.Tensor, th_reg: torch.Tensor, a: torch.Tensor | None) -> torch.Tensor:
        return rho * l2(th, th_reg, a)


class SeparateL2:
    """mu and rho apart, each with its optimizer and its weight: W_mu L2(mu) + W_rho L2(rho)."""

    name = "separate-l2"

    def __init__(self, model: torch.nn.Module, w_mu: float, w_rho: float):
        self.w_mu, self.w_rho = w_mu, w_rho
        flags = [torch.full((p.numel(),), is_rho(n), dtype=torch.bool) for n, p in model.named_parameters()]
        self.rho_mask = torch.cat(flags).to(next(model.parameters()).device)

    def groups(self, model: torch.nn.Module) -> list[list[torch.nn.Parameter]]:
        named = list(model.named_parameters())
        return [[p for n, p in named if not is_rho(n)], [p for n, p in named if is_rho(n)]]

    def split(self, th: torch.Tensor, th_reg: torch.Tensor, a: torch.Tensor | None):
        """(own, targets, weights) of the mu-parameters, then of the rho-parameters."""
        mu, rho = ~self.rho_mask, self.rho_mask
        a_mu, a_rho = (None, None) if a is None else (a[:, mu], a[:, rho])
        return (th[mu], th_reg[:, mu], a_mu), (th[rho], th_reg[:, rho], a_rho)

    def penalty(self, rho: float, th: torch.Tensor, th_reg: torch.Tensor, a: torch.Tensor | None) -> torch.Tensor:
        (m, m_reg, a_mu), (r, r_reg, a_rho) = self.split(th, th_reg, a)
        return self.w_mu * rho * l2(m, m_reg, a_mu) + self.w_rho * rho * l2(r, r_reg, a_rho)


class Algorithm2(SeparateL2):
    """The paper's Algorithm 2: W_mu L2(mu) + W_rho sum_j KL(N(0, sigma_i^2) || N(0, sigma_reg_j^2))."""

    name = "separate-kl"

    def penalty(self, rho: float, th: torch.Tensor, th_reg: torch.Tensor, a: torch.Tensor | None) -> torch.Tensor:
        (m, m_reg, a_mu), (r, r_reg, a_rho) = self.split(th, th_reg, a)
        sigma = F.softplus(r)[None, :].expand(len(th_reg), -1)
        kl = gaussian_kl(torch.zeros_like(sigma), sigma, 0.0, F.softplus(r_reg))
        return self.w_mu * rho * l2(m, m_reg, a_mu) + self.w_rho * rho * (kl.sum() if a_rho is None else (a_rho * kl).sum())


def regularization(model: torch.nn.Module, settings: RegularizationSettings) -> UniformL2 | SeparateL2:
    """The strategy ``settings`` names for ``model`` (a deterministic network has one: uniform-l2)."""
    if not isinstance(model, BayesNet) or settings.strategy == "uniform-l2":
        return UniformL2()
    if settings.strategy == "separate-l2":
        return SeparateL2(model, settings.w_mu, settings.w_rho)
    if settings.strategy == "separate-kl":
        return Algorithm2(model, settings.w_mu, settings.w_rho)
    raise ValueError(f"unknown regularization {settings.strategy!r}; allowed: uniform-l2, separate-l2, separate-kl")
