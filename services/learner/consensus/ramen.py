"""RAMEN's consensus (Zhao et al., RSS 2025): each parameter weighted by how often the data moved it.

Each node counts, per parameter, the optimizer steps that gave it a gradient from the data; the
counts travel in the State after the parameters. Each side's weight W = p c + q maps its count c
linearly onto [rho / 1000, rho]; the target is the W-weighted midpoint and the pull is W / rho
(penalty W_i (theta - z)^2, dual step 2 W_i W_j / (W_i + W_j) (theta_i - theta_j)). RAMEN
(``scaling_AUQ_CADMM``) takes p and q from the range of the two sides' summed counts, which works
for its hash grid, where many counts are 0; a dense network's counts are all far from 0, and that
scaling then gives negative weights (and a target that runs off to infinity): here the range is
that of both sides' counts. Counts alike everywhere give DiNNO's midpoint and weight.
"""

from __future__ import annotations

import torch


def ramen_targets(th_i: torch.Tensor, c_i: torch.Tensor, thj: torch.Tensor, cj: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per neighbour (rows of ``thj`` and its counts ``cj``), RAMEN's target and pull."""
    z = torch.empty_like(thj)
    a = torch.empty_like(thj)
    for row in range(len(thj)):
        lo = torch.minimum(c_i.min(), cj[row].min())
        hi = torch.maximum(c_i.max(), cj[row].max())
        if hi <= lo:
            z[row], a[row] = (th_i + thj[row]) / 2, 1.0
            continue
        p = (1 - 1e-3) / (hi - lo)  # in units of rho
        q = 1e-3 - p * lo
        w_i, w_j = p * c_i + q, p * cj[row] + q
        z[row] = (w_i * th_i + w_j * thj[row]) / (w_i + w_j)
        a[row] = w_i
    return z, a


class RamenRule:
    """RAMEN's weights from gradient counts, kept here and sent after the parameters."""

    name = "ramen"

    def __init__(self, param_count: int, device: torch.device):
        self.counts = torch.zeros(param_count, device=device)

    def start_round(self, k: int, theta: torch.Tensor, extra: torch.Tensor | None) -> None:
        self.counts = extra.clone()  # the counts the round's State carries

    def keep_for(self, rounds: int, timed: bool) -> int:
        return rounds

    def targets(self, ages, th_i, thj, extras):
        return ramen_targets(th_i, self.counts, thj, extras)

    def dual_step(self, rho: float, th_i: torch.Tensor, th_j: torch.Tensor, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return 2 * rho * a * (th_i - z)

    def data_loss(self, node) -> torch.Tensor | None:
        """Back-propagate the BCE alone and count the parameters it gave a gradient; the rest of the loss."""
        bce, rest = node.batch_terms()
        bce.backward()
        self.counts += torch.cat([(p.grad != 0).reshape(-1) for p in node.model.parameters()]).float()
        return rest

    def extra(self) -> list[torch.Tensor]:
        return [self.counts]
