"""Each part of the learner's own small settings, made from the ``learner`` section in one place.

The learner's config section (:class:`~swarmmap.shared.run.config.LearnerSettings`) is what a user
writes; the parts take only what they use: Algorithm 1 and the clock mode
:class:`~swarmmap.services.learner.exchange.ExchangeRules`, a node's loss and schedule
:class:`TrainingSettings`, DiNNO's update :class:`DinnoSettings`, and so on. Nothing else in the
learner reads the section's fields (the service passes these on).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from swarmmap.services.learner.exchange import ExchangeRules
from swarmmap.shared.plugins import load
from swarmmap.shared.run.config import LearnerSettings, consensus_options


def exchange_rules(s: LearnerSettings) -> ExchangeRules:
    """Algorithm 1's timeouts; a node keeps its States for the rounds a resumed neighbour may replay."""
    return ExchangeRules(peer_timeout=s.peer_timeout_s, resend_after=s.resend_after_s, silent_after=s.silent_after_s,
                         rejoin_wait=s.rejoin_wait_s, keep_rounds=-(-s.checkpoint_every // s.exchange_every) + 2,
                         round_wait=s.round_wait_s)


@dataclass(frozen=True)
class TrainingSettings:
    """A node's batch loss and learning-rate schedule."""

    rounds: int
    batch_size: int
    optimizer: str
    lr_schedule: str
    lr_start: float
    lr_finish: float
    kl_weight: float  # bnn: weight of the KL to the prior
    unseen_weight: float  # bnn: weight of the noise-contrastive prior away from the data (0: off)
    unseen_points: int
    unseen_draws: int
    unseen_prior_std: float

    @classmethod
    def of(cls, s: LearnerSettings) -> TrainingSettings:
        return cls(s.rounds, s.batch_size, s.optimizer, s.lr_schedule, s.lr_start, s.lr_finish, s.kl_weight,
                   s.unseen_weight, s.unseen_points, s.unseen_draws, s.unseen_prior_std)


@dataclass(frozen=True)
class DinnoSettings:
    """DiNNO's node update: rho, the primal loop, how long a neighbour's State keeps pulling.

    ``keep_for``: rounds a neighbour's newest State pulls when no newer one comes (at least
    ``exchange_every``; on a clock, with ``stale_rounds`` 0, until it is forgotten); its dual
    stays in the objective as long (a consensus rule may keep the State longer, without it)."""

    rho_init: float
    rho_growth: float
    primal_iterations: int
    optimizer_per_round: bool
    keep_for: int
    timed: bool  # exchange on a clock

    @classmethod
    def of(cls, s: LearnerSettings) -> DinnoSettings:
        timed = s.exchange_every_s > 0 and s.stale_rounds == 0
        keep_for = s.rounds + 1 if timed else max(s.stale_rounds, s.exchange_every)
        return cls(s.rho_init, s.rho_growth, s.primal_iterations, s.optimizer_per_round, keep_for, timed)


@dataclass(frozen=True)
class ConsensusSettings:
    """The consensus rule's knobs: sigma's fields, and a plug-in's own options (learner.consensus_options,
    validated by the rule's options model; None for a rule that takes none)."""

    min_weight: float = 0.05  # sigma: a pull stays within [this, 2 - this] x DiNNO's
    memory_rounds: int = 100  # sigma: how long an outdated State keeps pulling, its sigma widened
    max_weight: float | None = None  # sigma: at most this x DiNNO's pull, the target as far (None: 2 - min_weight, the pull only)
    options: Any = None

    @classmethod
    def of(cls, s: LearnerSettings) -> ConsensusSettings:
        options = consensus_options(s.consensus, load("consensus", s.consensus), s.consensus_options)
        return cls(s.consensus_min_weight, s.sigma_memory_rounds, min(s.sigma_max_weight, 2 - s.consensus_min_weight)
                   if s.robust else None, options)


@dataclass(frozen=True)
class RobustSettings:
    """Robust consensus (:mod:`~swarmmap.services.learner.robust`); ``on`` False: none."""

    on: bool = True
    spread_factor: float = 4.0
    pull_factor: float = 3.0

    @classmethod
    def of(cls, s: LearnerSettings) -> RobustSettings:
        return cls(s.robust, s.robust_spread_factor, s.robust_pull_factor)


@dataclass(frozen=True)
class RegularizationSettings:
    """The paper's Figure 7: how a Bayesian network's consensus term treats mu and rho."""

    strategy: str  # uniform-l2, separate-l2 or separate-kl (Algorithm 2)
    w_mu: float = 1.0
    w_rho: float = 1.0

    @classmethod
    def of(cls, s: LearnerSettings) -> RegularizationSettings:
        return cls(s.regularization, s.w_mu, s.w_rho)


@dataclass(frozen=True)
class ScheduleSettings:
    """Which training rounds exchange, evaluate and checkpoint."""

    rounds: int
    exchange_every: int
    eval_every: int
    checkpoint_every: int
    online: bool  # train on a sliding window of the newest scans
    window_scans: int

    @classmethod
    def of(cls, s: LearnerSettings) -> ScheduleSettings:
        return cls(s.rounds, s.exchange_every, s.eval_every, s.checkpoint_every, s.data == "online", s.window_scans)
