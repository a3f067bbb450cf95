"""Sigma consensus: a Bayesian network's own posterior spread decides who moves towards whom.

For each Bayesian mean, the product of the two Gaussians N(mu_i, sigma_i^2) and N(mu_j, sigma_j^2)
has its mean at the precision-weighted midpoint z = mu_i + s (mu_j - mu_i),
s = sigma_i^2 / (sigma_i^2 + sigma_j^2), which this node approaches with weight a = 2 s, clamped
to [min_weight, 2 - min_weight] (1 where they are equally sure, as DiNNO; towards 2 where this
node is the less sure). Every other parameter (rho itself, the sine layer, the output layer) is
pulled towards DiNNO's midpoint with weight 1. The dual step rho a (2 - a) (theta_i - theta_j) is
the same at both ends of the link up to sign (a_ji = 2 - a_ij), so the two duals of a link cancel
as DiNNO's do; an unbalanced pair would push the whole team off the data's optimum.

Memory (``memory_rounds``): a lost link's State is an older measurement, not nothing. A
neighbour's newest State keeps pulling for that many rounds, its variance widened as a Kalman
prediction step would: sigma_j^2 + t^2 m^2 + t v, with m and v the mean and variance of this
node's own per-round move of that parameter (smoothed, weight 0.9). Its pull weakens with age
and has no floor; parameters without a posterior take the mean discount.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def sigma_pairs(model: torch.nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each Bayesian mean (``*_mu``) and its rho (``*_rho``) lie in the flat parameter vector."""
    offsets, at = {}, 0
    for name, p in model.named_parameters():
        offsets[name] = (at, p.numel())
        at += p.numel()
    mu, rho = [], []
    for name, (start, count) in offsets.items():
        partner = offsets.get(name[:-3] + "_rho") if name.endswith("_mu") else None
        if partner is not None:
            mu.append(torch.arange(start, start + count))
            rho.append(torch.arange(partner[0], partner[0] + count))
    if not mu:
        raise ValueError("consensus sigma needs a Bayesian network (parameters *_mu with their *_rho)")
    device = next(model.parameters()).device
    return torch.cat(mu).to(device), torch.cat(rho).to(device)


def sigma_targets(th_i: torch.Tensor, thj: torch.Tensor, mu_at: torch.Tensor, rho_at: torch.Tensor,
                  min_weight: float, widen: torch.Tensor | None = None, max_weight: float | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per neighbour (rows of ``thj``), the target and weight of every parameter.

    ``widen`` (one row per neighbour, one column per mean; None: every State is this round's)
    is what each outdated State's variance has grown by (:meth:`SigmaRule.widening`).
    ``max_weight`` (robust consensus) bounds what a neighbour's self-reported certainty buys it:
    the share s within [1 - max_weight / 2, max_weight / 2], so the weight at most max_weight and
    the target at most that far of the way (None: the weight clamped to 2 - min_weight only)."""
    var_i = F.softplus(th_i[rho_at]).square()
    var_j = F.softplus(thj[:, rho_at]).square()
    share = torch.full_like(thj, 0.5)
    floor = torch.full((len(thj), 1), min_weight, dtype=thj.dtype, device=thj.device)
    if widen is None:
        share[:, mu_at] = var_i / (var_i + var_j)
    else:
        both = var_i + var_j
        share *= (both / (both + widen)).mean(1, keepdim=True)
        share[:, mu_at] = var_i / (both + widen)
        floor[(widen > 0).any(1)] = 0.0
    if max_weight is not None:  # both ends of a link clamp alike (s_ji = 1 - s_ij): its two duals still cancel
        lo = torch.full((len(thj), 1), 1 - max_weight / 2, dtype=thj.dtype, device=thj.device)
        if widen is not None:
            lo[(widen > 0).any(1)] = 0.0  # an outdated State's pull keeps weakening with age: no floor
        share[:, mu_at] = torch.minimum(torch.maximum(share[:, mu_at], lo), torch.full_like(lo, max_weight / 2))
    z = th_i + share * (thj - th_i)
    a = 2 * share
    a[:, mu_at] = torch.maximum(a[:, mu_at], floor).clamp(max=2 - min_weight)
    return z, a


class SigmaRule:
    """Sigma consensus at one node: the model's mu/rho pairs and the drift of its own parameters."""

    name = "sigma"

    def __init__(self, model: torch.nn.Module, min_weight: float, memory_rounds: int, max_weight: float | None = None):
        self.mu_at, self.rho_at = sigma_pairs(model)
        self.min_weight, self.memory_rounds, self.max_weight = min_weight, memory_rounds, max_weight
        # each parameter's move a round, smoothed over rounds (its mean and mean square)
        self.drift: tuple[torch.Tensor, torch.Tensor] | None = None
        self.last_theta: tuple[int, torch.Tensor] | None = None

    def start_round(self, k: int, theta: torch.Tensor, extra: torch.Tensor | None) -> None:
        """Smooth each parameter's move over the last round into ``drift`` (weight 0.9 to the
        past); a round missed (resumed) starts the smoothing afresh."""
        if self.last_theta is not None and self.last_theta[0] == k - 1:
            moved = theta - self.last_theta[1]
            if self.drift is None:
                self.drift = (moved, torch.square(moved))
            else:
                self.drift[0].mul_(0.9).add_(moved, alpha=0.1)
                self.drift[1].mul_(0.9).addcmul_(moved, moved, value=0.1)
        self.last_theta = (k, theta.clone())

    def keep_for(self, rounds: int, timed: bool) -> int:
        return rounds if timed else max(rounds, self.memory_rounds)

    def widening(self, ages: torch.Tensor) -> torch.Tensor:
        """How much the variance of each mean of a State ``ages`` rounds old (one row per
        neighbour) has grown since it was sent: a parameter that moves d a round, with mean m and
        variance v = E[d^2] - m^2, may have moved t m by a steady drift and by noise of variance
        t v: t^2 m^2 + t v (a Kalman filter's prediction step, velocity and noise)."""
        mean, square = (x[self.mu_at] for x in self.drift)
        steady = torch.square(mean)
        t = ages[:, None]
        return t * t * steady[None] + t * (square - steady).clamp(min=0)[None]

    def targets(self, ages, th_i, thj, extras):
        widen = None if self.drift is None or not bool((ages > 0).any()) else self.widening(ages)
        return sigma_targets(th_i, thj, self.mu_at, self.rho_at, self.min_weight, widen, self.max_weight)

    def dual_step(self, rho: float, th_i: torch.Tensor, th_j: torch.Tensor, z, a: torch.Tensor) -> torch.Tensor:
        return rho * a * (2 - a) * (th_i - th_j)

    def data_loss(self, node) -> torch.Tensor | None:
        return node.batch_loss()

    def extra(self) -> list[torch.Tensor]:
        return []
