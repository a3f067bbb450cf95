"""The interface of a consensus rule: how hard each parameter is pulled towards each neighbour.

DiNNO's consensus term for node i is rho x sum_j ||theta - z_ij||^2 plus a dual per link j. A
rule gives, for every neighbour j whose State the node holds, a target z_ij and a weight a_ij per
parameter (penalty rho x sum_j a_ij (theta - z_ij)^2; a weight of None means 1 everywhere) and the
link's dual step. Rules: :mod:`.dinno` (DiNNO exactly), :mod:`.ramen` (RAMEN's gradient counts),
:mod:`.sigma` (the Bayesian network's own posterior spread), :mod:`.dgvi` (DGVI's pooled Gaussians).

Adding a rule: a class with these methods and a :class:`~swarmmap.shared.plugins.ConsensusPlugin`
naming it (its models, whether its State carries a vector after the parameters, its options),
registered as an entry point in the group ``swarmmap.consensus``: here, a module of its own, a
spec in :mod:`.builtin` and a line in swarmmap's ``pyproject.toml``; from another package, the
same in that package (docs/layout.md).
"""

from __future__ import annotations

from typing import Protocol

import torch


class ConsensusRule(Protocol):
    """One node's consensus rule; it may keep state of its own (counts, drift)."""

    name: str

    def start_round(self, k: int, theta: torch.Tensor, extra: torch.Tensor | None) -> None:
        """Training round ``k`` starts from ``theta`` (and what the State carries after it)."""

    def keep_for(self, rounds: int, timed: bool) -> int:
        """How many rounds a neighbour's newest State keeps pulling (``rounds``: DiNNO's)."""

    def targets(self, ages: torch.Tensor, th_i: torch.Tensor, thj: torch.Tensor, extras: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Each neighbour's (a row of ``thj``, its State ``ages`` rounds old) target and weights."""

    def dual_step(self, rho: float, th_i: torch.Tensor, th_j: torch.Tensor, z: torch.Tensor, a: torch.Tensor | None
                  ) -> torch.Tensor:
        """What a link's dual gains this round."""

    def data_loss(self, node) -> torch.Tensor | None:
        """The batch loss of ``node`` (a LocalNode) to add the consensus terms to; None when it
        was back-propagated already (a rule that reads the data's gradients)."""

    def extra(self) -> list[torch.Tensor]:
        """What this node's State carries after its parameters."""


class PlainLoss:
    """Mixin: the node's batch loss as it is, nothing after the parameters, no state to start."""

    def start_round(self, k: int, theta: torch.Tensor, extra: torch.Tensor | None) -> None:
        pass

    def keep_for(self, rounds: int, timed: bool) -> int:
        return rounds

    def data_loss(self, node) -> torch.Tensor | None:
        return node.batch_loss()

    def extra(self) -> list[torch.Tensor]:
        return []
