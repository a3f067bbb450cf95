"""DiNNO's node update (Yu, Vincent & Schwager 2022): duals, rho and the primal loop.

Per round k, for node i with neighbour parameters theta_j (as DiNNO's ``optimizers/dinno.py``):
rho <- rho_init x growth^(k+1); a dual step per link p_ij += rho (theta_i - theta_j) (one dual
per link, as UDON: a lost link's dual is left out, not mixed in); targets
theta_reg_j = (theta_i + theta_j) / 2; then ``primal_iterations`` optimizer steps on
``loss(batch) + <theta, sum_j p_ij> + rho * sum_j ||theta - theta_reg_j||^2`` with an optimizer
re-created each round (or kept) whose learning rate follows the schedule. A node without
neighbours takes plain loss steps.

What DiNNO fixes, the parts here make a choice of: the consensus rule gives each link's targets,
weights and dual step (:mod:`~swarmmap.services.learner.consensus`: dinno, ramen, sigma) and the
regularisation strategy the penalty and the optimizer groups
(:mod:`~swarmmap.services.learner.regularization`: the paper's Figure 7, Algorithm 2 among them).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from swarmmap.services.learner.consensus.base import ConsensusRule
from swarmmap.services.learner.node import LocalNode, NodeInputs
from swarmmap.services.learner.optim import Optimizer, make_optimizer
from swarmmap.services.learner.regularization import UniformL2
from swarmmap.services.learner.robust import PullBound
from swarmmap.services.learner.settings import DinnoSettings
from swarmmap.shared.learning.models import set_flat


class DinnoNode(LocalNode):
    """One node's model, data, duals and rho; :meth:`update` is Algorithm 1's NODEUPDATE.

    ``public()`` (None: the node's own parameters) is what the neighbours hold of this node's
    State where it differs from it (compression with error feedback: the sender's replica).
    ``bound`` (robust consensus) clips each link's pull and dual."""

    def __init__(self, inputs: NodeInputs, dinno: DinnoSettings, rule: ConsensusRule, reg: UniformL2,
                 public: Callable[[], np.ndarray | None] | None = None, bound: PullBound | None = None):
        super().__init__(inputs)
        self.d, self.rule, self.reg = dinno, rule, reg
        self.public, self.bound = public, bound
        self.rho = dinno.rho_init
        self.duals: dict[int, torch.Tensor] = {}  # one per link
        self.groups = reg.groups(self.model)
        self.optimizers = None if dinno.optimizer_per_round else self._optimizers(self.lr(0))
        # Each neighbour's newest State: (round it arrived, parameters, what comes after them); it
        # keeps pulling for keep_for rounds when no newer one comes, its dual for duals_for rounds.
        self.known: dict[int, tuple[int, torch.Tensor, torch.Tensor | None]] = {}
        self.duals_for = dinno.keep_for
        self.keep_for = rule.keep_for(dinno.keep_for, dinno.timed)

    def extra(self) -> list[torch.Tensor]:
        return self.rule.extra()

    def checkpoint(self) -> dict:
        doc = super().checkpoint()
        doc.update(duals={j: d.cpu() for j, d in self.duals.items()}, rho=self.rho,
                   optimizers=None if self.optimizers is None else [o.state_dict() for o in self.optimizers])
        return doc

    def restore(self, doc: dict) -> None:
        super().restore(doc)
        self.duals = {int(j): d.to(self.device) for j, d in doc["duals"].items()}
        self.rho = doc["rho"]
        if self.optimizers is not None and doc.get("optimizers") is not None:
            for opt, state in zip(self.optimizers, doc["optimizers"]):
                opt.load_state_dict(state)

    def _optimizers(self, lr: float) -> list[Optimizer]:
        return [make_optimizer(self.t.optimizer, group, lr) for group in self.groups if group]

    def update(self, k: int, state_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """One DiNNO round given neighbours' States of round ``k`` (an exchange round): a dual step
        per link whose State came, then the primal steps against every neighbour whose newest
        State is recent enough."""
        n = self.layout.param_count
        self._start_round(k, state_i)
        if peers:
            stj = torch.from_numpy(np.stack(list(peers.values()))).to(self.device)
            for row, j in enumerate(peers):
                self.known[j] = (k, stj[row, :n], stj[row, n:] if self.layout.copies > 1 else None)
        self._primal(k, fresh=peers.keys())
        return self.state()

    def local_update(self, k: int, state_i: np.ndarray) -> np.ndarray:
        """A round between exchanges: the primal steps against the neighbours' newest States
        (their targets recomputed from this node's parameters now), the duals as they were."""
        self._start_round(k, state_i)
        self._primal(k, fresh=())
        return self.state()

    def forget(self, j: int) -> None:
        """Stop pulling towards neighbour ``j``'s last State (it went silent); its dual is kept
        aside, as for a lost link, for when it sends again."""
        self.known.pop(j, None)

    def _start_round(self, k: int, state_i: np.ndarray) -> None:
        """Load the State the round starts from, tell the rule, set the round's rho."""
        n = self.layout.param_count
        st = torch.as_tensor(state_i, device=self.device)
        set_flat(self.model, st[:n])
        self.rule.start_round(k, st[:n], st[n:] if self.layout.copies > 1 else None)
        self.rho = self.d.rho_init * self.d.rho_growth ** (k + 1)  # from the round: a node that caught up has the team's rho
        self.begin_round(k)

    def public_params(self, own: torch.Tensor) -> torch.Tensor:
        """The parameters the consensus terms take for this node: ``own``, or, where its States
        are compressed with error feedback, the copy its neighbours hold (as CHOCO-SGD): both ends
        of a link then compute its dual from the same two vectors, so the duals stay balanced,
        and what compression has not yet carried does not brake the team."""
        public = self.public() if self.public is not None else None
        if public is None:
            return own
        return torch.from_numpy(np.array(public[: self.layout.param_count], dtype=np.float32)).to(self.device)

    def consensus(self, k: int, fresh) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor] | None:
        """This round's targets, weights and summed duals, after a dual step per link in
        ``fresh`` (never against an outdated State); None without neighbours' States. Duals
        count only for links whose State is at most ``duals_for`` rounds old."""
        for j in [j for j, (arrived, _, _) in self.known.items() if k - arrived >= self.keep_for]:
            del self.known[j]  # a neighbour gone, or a link that has stayed down
        if not self.known:
            return None
        ids = sorted(self.known)
        thj = torch.stack([self.known[j][1] for j in ids])
        extras = torch.stack([self.known[j][2] for j in ids]) if self.layout.copies > 1 else None
        th_i = self.public_params(torch.nn.utils.parameters_to_vector(self.model.parameters()).detach())
        if self.bound is not None:
            thj = self.bound.rows(th_i, thj)
        ages = torch.tensor([k - self.known[j][0] for j in ids], dtype=th_i.dtype, device=self.device)
        th_reg, a = self.rule.targets(ages, th_i, thj, extras)
        for row, j in enumerate(ids):
            if j in fresh:
                step = self.rule.dual_step(self.rho, th_i, thj[row], th_reg[row], None if a is None else a[row])
                self.duals[j] = self.duals.get(j, torch.zeros_like(th_i)) + step
        if self.bound is not None:
            self.bound.duals(self.duals)
        heard = [j for j in ids if k - self.known[j][0] < self.duals_for]  # the links this node hears from
        duals = torch.stack([self.duals[j] for j in heard]).sum(0) if heard else torch.zeros_like(th_i)
        return th_reg, a, duals

    def _primal(self, k: int, fresh) -> None:
        """``primal_iterations`` optimizer steps on the loss plus the consensus terms."""
        terms = self.consensus(k, fresh)
        lr = self.lr(k)
        if self.optimizers is None:
            optimizers = self._optimizers(lr)
        else:
            optimizers = self.optimizers
            for opt in optimizers:
                for group in opt.param_groups:
                    group["lr"] = lr
        for _ in range(self.d.primal_iterations):
            for opt in optimizers:
                opt.zero_grad()
            loss = self.rule.data_loss(self)
            if terms is not None:
                th_reg, a, duals = terms
                th = torch.nn.utils.parameters_to_vector(self.model.parameters())
                extra = torch.dot(th, duals) + self.reg.penalty(self.rho, th, th_reg, a)
                loss = extra if loss is None else loss + extra
            if loss is not None:
                loss.backward()  # one backward of the sum: both groups' gradients before either step
            for opt in optimizers:
                opt.step()
