"""DiNNO's node update (Yu, Vincent & Schwager 2022) and the paper's Algorithm 2, free of any transport.

Per round k, for node i with neighbour parameters theta_j (as DiNNO's ``optimizers/dinno.py``):
rho <- rho * growth; duals p_i += rho * sum_j (theta_i - theta_j); targets
theta_reg_j = (theta_i + theta_j) / 2; then ``primal_iterations`` optimizer steps on
``loss(batch) + <theta, p_i> + rho * sum_j ||theta - theta_reg_j||^2`` with an optimizer
re-created each round (or kept) whose learning rate follows the schedule. A node without
neighbours takes plain loss steps. ``loss`` is BCE, plus ``kl_weight`` x the KL to the prior
for a Bayesian network (the paper's equation 7).

For a Bayesian network the consensus term follows ``regularization`` (the paper's Figure 7):
``uniform-l2`` treats every parameter alike (one optimizer, as above); ``separate-l2`` and
``separate-kl`` give the mu-parameters and the rho-parameters an optimizer each and weigh
their penalties by W_mu = w_mu x rho and W_rho = w_rho x rho. ``separate-kl`` is Algorithm 2:
L2 for mu, and for rho the KL divergence (equation 6) between N(0, softplus(rho_i)^2) and
N(0, softplus(rho_reg_j)^2) summed over parameters and neighbours: the two Gaussians share
their mean, so the term pulls only the spreads together, on the scale of the spreads rather
than of raw rho values. Both losses are back-propagated before either optimizer steps, so rho
also learns from the prediction loss.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F

from swarmmap.shared.bnn import BayesNet, DropoutPlan, function_prior_kl, gaussian_kl, is_rho, sampled_logits
from swarmmap.shared.config import LearnerSettings
from swarmmap.shared.models import DropoutNet, StochasticNet, flatten_into, set_flat
from swarmmap.shared.unseen import Coverage


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


def warm_up(optimizer: str) -> None:
    """Load now what a node's first optimizer step would load: making the first torch optimizer
    imports torch's compiler stack, about 1.5 s of one core. Done before Algorithm 1 starts
    (while the robots drive), it does not slow round 0 (with 32 learners on 2 cores that round
    took 30 s). Draws no random numbers and keeps nothing."""
    p = torch.zeros(1, requires_grad=True)
    opt = make_optimizer(optimizer, [p], 1e-3)
    (2 * p).sum().backward()
    opt.step()


class Node(Protocol):
    """What Algorithm 1 and the services know of a learning rule (DiNNO, DSGD, DSGT): the seam
    between the exchange and the algorithm, so that nobody else guesses a State's layout."""

    model: torch.nn.Module

    def update(self, k: int, state: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """NODEUPDATE of round ``k`` given the neighbours' States of that round; the new State."""

    def state(self) -> np.ndarray:
        """The State this node sends now."""

    def params_of(self, state: np.ndarray) -> np.ndarray:
        """The model parameters inside a State."""

    def state_size(self) -> int:
        """Values in a State."""

    def rejoin(self, own: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """The State to go on from after catching up with the team."""

    def checkpoint(self) -> dict: ...

    def restore(self, doc: dict) -> None: ...


def state_copies(settings: LearnerSettings) -> int:
    """How many parameter-sized vectors a State holds (DSGT: theta and its tracker; RAMEN's
    consensus: theta and its gradient counts)."""
    return 2 if settings.algorithm == "dsgt" or (settings.algorithm == "dinno" and settings.consensus == "ramen") else 1


class LocalNode:
    """A node's model, its local data and the loss on a random batch of it.

    With a Bayesian network and ``unseen_weight`` > 0, the loss also holds a noise-contrastive
    prior on points away from the data (:attr:`coverage`, over the map's ``bounds``)."""

    def __init__(self, model: torch.nn.Module, points: torch.Tensor, labels: torch.Tensor,
                 settings: LearnerSettings, seed: int, bounds: tuple[float, float, float, float] | None = None):
        self.model = model
        self.device = next(model.parameters()).device
        self.points = points.to(self.device)
        self.labels = labels.to(self.device)
        self.s = settings
        self.new_state: Callable[[int], np.ndarray] = lambda n: np.empty(n, np.float32)  # set by a transport
        # What the neighbours hold of this node's State when it differs from the State itself (topk
        # compression: the sender's replica); set by the learner.
        self.public: Callable[[], np.ndarray | None] = lambda: None
        self.lrs = lr_schedule(settings.lr_schedule, settings.lr_start, settings.lr_finish, settings.rounds)
        self.gen = torch.Generator(device="cpu").manual_seed(seed)
        self.bayesian = isinstance(model, BayesNet)
        self.noise: torch.Generator | None = None
        if isinstance(model, StochasticNet):  # weight draws or dropout masks: the node's own stream
            self.noise = torch.Generator(device=self.device).manual_seed(seed + 7_000_003)
            model.use_generator(self.noise)
        self.coverage: Coverage | None = None  # where the noise-contrastive prior samples its points
        if self.bayesian and settings.unseen_weight > 0:
            if bounds is None:
                raise ValueError("learner.unseen_weight needs the map's bounds (where the unseen space lies)")
            self.coverage = Coverage(bounds, settings.unseen_margin_m, self.points.cpu().numpy())

    def checkpoint(self) -> dict:
        """Everything besides the parameters that the next rounds depend on (RNG states too, so
        a resumed run repeats the uninterrupted one)."""
        doc = {"gen": self.gen.get_state(), "noise": None if self.noise is None else self.noise.get_state()}
        if self.coverage is not None:
            doc["coverage"] = self.coverage.others.copy()
        return doc

    def restore(self, doc: dict) -> None:
        self.gen.set_state(doc["gen"])
        if self.noise is not None and doc.get("noise") is not None:
            self.noise.set_state(doc["noise"])
        if self.coverage is not None and doc.get("coverage") is not None and doc["coverage"].shape == self.coverage.shape:
            self.coverage.merge_cells(doc["coverage"])

    def set_data(self, points: np.ndarray, labels: np.ndarray) -> None:
        """Replace the local data (online training's sliding window)."""
        self.points = torch.from_numpy(np.ascontiguousarray(points)).to(self.device)
        self.labels = torch.from_numpy(np.ascontiguousarray(labels)).to(self.device)
        if self.coverage is not None:
            self.coverage.set_points(points)

    def state(self) -> np.ndarray:
        """What this node sends as its State: its flat parameters, written once into a vector
        from ``new_state`` (the transport's payload buffer, where it has one)."""
        return flatten_into(list(self.model.parameters()), self.new_state(self.state_size()))

    def params(self) -> np.ndarray:
        """The node's model parameters (a prefix of its State for DSGT)."""
        return flatten_into(list(self.model.parameters()), np.empty(self.param_count, np.float32))

    def params_of(self, state: np.ndarray) -> np.ndarray:
        """The model parameters inside a State of this node's kind."""
        return state[: self.param_count]

    @property
    def param_count(self) -> int:
        return sum(p.numel() for p in self.model.parameters())

    def state_size(self) -> int:
        """Values in a State of this node's kind."""
        return state_copies(self.s) * self.param_count

    def rejoin(self, own: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """The state a node that was away starts from when it catches up with its team: its own,
        from its checkpoint (a few rounds old while its neighbours wait ``rejoin_wait_s`` for it;
        consensus pulls it in). Measured against the mean of its own and its neighbours' States,
        which wipes out what it alone had learnt of its part of the plan (tests/e2e/test_failures.py)."""
        return own

    def batch_loss(self) -> torch.Tensor:
        """BCE on a random batch, plus kl_weight x KL to the prior for a Bayesian network."""
        bce, kl = self.batch_terms()
        return bce if kl is None else bce + kl

    def batch_terms(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The batch loss's two terms: BCE on a random batch, and kl_weight x KL to the prior
        (None for a deterministic network)."""
        idx = torch.randint(0, len(self.points), (min(self.s.batch_size, len(self.points)),), generator=self.gen)
        idx = idx.to(self.device)
        bce = F.binary_cross_entropy_with_logits(self.model.logits(self.points[idx]), self.labels[idx])
        kl = self.s.kl_weight * self.model.kl() if self.bayesian and self.s.kl_weight > 0 else None
        away = self.unseen_term()
        return bce, away if kl is None else kl if away is None else kl + away

    def begin_round(self, k: int) -> None:
        """Take in what the team's States of rounds before ``k`` said they cover."""
        if self.coverage is not None:
            self.coverage.advance(k)

    def unseen_term(self) -> torch.Tensor | None:
        """``unseen_weight`` x the noise-contrastive prior's KL at ``unseen_points`` points drawn
        where no robot known to this node has data (None when off or nothing is uncovered)."""
        if self.coverage is None:
            return None
        xy = self.coverage.sample(self.s.unseen_points, self.gen, self.device)
        if xy is None:
            return None
        logits = sampled_logits(self.model, xy, self.s.unseen_draws, self.noise)
        return self.s.unseen_weight * function_prior_kl(logits, self.s.unseen_prior_std)

    def gradient(self) -> torch.Tensor:
        """The flat gradient of the batch loss at the current parameters."""
        self.model.zero_grad()
        self.batch_loss().backward()
        return torch.cat([p.grad.reshape(-1) for p in self.model.parameters()]).detach().clone()


class DinnoNode(LocalNode):
    """One node's model, data, duals and rho; :meth:`update` is Algorithm 1's NODEUPDATE.

    ``consensus`` weighs each parameter's pull towards each neighbour j by a per-parameter
    factor a_ij and a target z_ij (see the README's "Consensus weights"): penalty
    rho x sum_j a_ij (theta - z_ij)^2 and a dual step per link (:meth:`dual_step`). ``dinno``:
    a = 1, z the midpoint (DiNNO exactly). ``ramen``: RAMEN's weights from how many steps gave
    each parameter a gradient (the counts travel in the State, after the parameters).
    ``sigma``: z the precision-weighted midpoint of the two posteriors' means and
    a_ij = 2 sigma_i^2 / (sigma_i^2 + sigma_j^2), clamped to [m, 2 - m]: a node moves towards its
    neighbour where it is less sure than the neighbour, and stays where it is surer."""

    def __init__(self, model: torch.nn.Module, points: torch.Tensor, labels: torch.Tensor,
                 settings: LearnerSettings, seed: int, bounds: tuple[float, float, float, float] | None = None):
        super().__init__(model, points, labels, settings, seed, bounds)
        self.rho = settings.rho_init
        self.duals: dict[int, torch.Tensor] = {}  # one per link (as UDON): a lost link's dual is left out, not mixed in
        names = [n for n, _ in model.named_parameters()]
        params = list(model.parameters())
        rho_flags = torch.cat([torch.full((p.numel(),), is_rho(n), dtype=torch.bool) for n, p in zip(names, params)])
        self.rho_mask = rho_flags.to(self.device)
        self.strategy = settings.regularization if self.bayesian else "uniform-l2"
        if self.strategy == "uniform-l2":
            self.groups = [params]
        else:
            self.groups = [[p for n, p in zip(names, params) if not is_rho(n)], [p for n, p in zip(names, params) if is_rho(n)]]
        self.optimizers = None if settings.optimizer_per_round else self._optimizers(float(self.lrs[0]))
        self.mu_at, self.rho_at = sigma_pairs(model) if self.s.consensus == "sigma" else (None, None)
        self.counts = torch.zeros(self.param_count, device=self.device) if self.s.consensus == "ramen" else None
        # Each neighbour's newest State: (round it arrived, parameters, RAMEN counts); it keeps pulling
        # for stale_rounds rounds (at least exchange_every) when no newer one comes; on a clock
        # (exchange_every_s), with stale_rounds 0, until a newer one comes or it is forgotten.
        self.known: dict[int, tuple[int, torch.Tensor, torch.Tensor | None]] = {}
        timed = settings.exchange_every_s > 0 and settings.stale_rounds == 0
        self.keep_for = settings.rounds + 1 if timed else max(settings.stale_rounds, settings.exchange_every)
        self.duals_for = self.keep_for  # a link's dual is in the objective while its State is this recent
        # sigma: each parameter's move a round, smoothed over rounds (its mean and mean square); an
        # outdated State's sigma is widened by how far it may have moved since (see widening)
        self.drift: tuple[torch.Tensor, torch.Tensor] | None = None
        self.last_theta: tuple[int, torch.Tensor] | None = None
        if self.s.consensus == "sigma" and not timed:
            self.keep_for = max(self.keep_for, settings.sigma_memory_rounds)

    def state(self) -> np.ndarray:
        """[theta], or with RAMEN's consensus [theta, gradient counts]."""
        extra = [self.counts] if self.counts is not None else []
        return flatten_into([*self.model.parameters(), *extra], self.new_state(self.state_size()))

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

    def _optimizers(self, lr: float) -> list[torch.optim.Optimizer]:
        return [make_optimizer(self.s.optimizer, group, lr) for group in self.groups if group]

    def mu_rho_split(self) -> tuple[int, int]:
        """How many parameters are mu and how many rho (Algorithm 2's two groups)."""
        n_rho = int(self.rho_mask.sum())
        return self.rho_mask.numel() - n_rho, n_rho

    def consensus_penalty(self, th: torch.Tensor, th_reg: torch.Tensor, a: torch.Tensor | None = None) -> torch.Tensor:
        """The round's pull towards the neighbours' targets ``th_reg`` (one row per neighbour),
        each parameter's weighted by ``a`` (same shape; None: 1 everywhere)."""

        def l2(x: torch.Tensor, target: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
            sq = torch.square(x[None, :] - target)
            return torch.sum(sq if w is None else w * sq)

        if self.strategy == "uniform-l2":
            return self.rho * l2(th, th_reg, a)
        mu, rho = ~self.rho_mask, self.rho_mask
        a_mu, a_rho = (None, None) if a is None else (a[:, mu], a[:, rho])
        penalty = self.s.w_mu * self.rho * l2(th[mu], th_reg[:, mu], a_mu)
        if self.strategy == "separate-l2":
            return penalty + self.s.w_rho * self.rho * l2(th[rho], th_reg[:, rho], a_rho)
        sigma = F.softplus(th[rho])[None, :].expand(len(th_reg), -1)
        kl = gaussian_kl(torch.zeros_like(sigma), sigma, 0.0, F.softplus(th_reg[:, rho]))
        return penalty + self.s.w_rho * self.rho * (kl.sum() if a_rho is None else (a_rho * kl).sum())

    def targets(self, k: int, ids: list[int], th_i: torch.Tensor, thj: torch.Tensor, cj: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Each neighbour's (``ids``, rows of ``thj``) target z_ij and weights a_ij (None: DiNNO's,
        1 everywhere) in round ``k``."""
        if self.s.consensus == "dinno":
            return (thj + th_i) / 2, None
        if self.s.consensus == "ramen":
            return ramen_targets(th_i, self.counts, thj, cj)
        ages = torch.tensor([k - self.known[j][0] for j in ids], dtype=th_i.dtype, device=self.device)
        widen = None if self.drift is None or not bool((ages > 0).any()) else self.widening(ages)
        return sigma_targets(th_i, thj, self.mu_at, self.rho_at, self.s.consensus_min_weight, widen)

    def update(self, k: int, state_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """One DiNNO round for this node given neighbours' States of round ``k`` (an exchange
        round): a dual step per link whose State came, then the primal steps against every
        neighbour whose newest State is recent enough (``stale_rounds``; 0: this round's only)."""
        n = self.param_count
        self._start_round(k, state_i)
        if peers:
            stj = torch.from_numpy(np.stack(list(peers.values()))).to(self.device)
            for row, j in enumerate(peers):
                self.known[j] = (k, stj[row, :n], stj[row, n:] if self.counts is not None else None)
        self._primal(k, fresh=peers.keys())
        return self.state()

    def local_update(self, k: int, state_i: np.ndarray) -> np.ndarray:
        """A round between exchanges (``exchange_every`` > 1): the primal steps against the
        neighbours' newest States (their targets recomputed from this node's parameters now),
        the duals left as the last exchange made them."""
        self._start_round(k, state_i)
        self._primal(k, fresh=())
        return self.state()

    def _start_round(self, k: int, state_i: np.ndarray) -> None:
        """Load the State the round starts from (and RAMEN's counts) and the round's rho."""
        n = self.param_count
        st = torch.as_tensor(state_i, device=self.device)
        set_flat(self.model, st[:n])
        if self.counts is not None:
            self.counts = st[n:].clone()
        if self.s.consensus == "sigma":
            self._track_drift(k, st[:n])
        self.rho = self.s.rho_init * self.s.rho_growth ** (k + 1)  # from the round: a node that caught up has the team's rho
        self.begin_round(k)

    def _track_drift(self, k: int, theta: torch.Tensor) -> None:
        """Smooth each parameter's move over the last round into ``drift`` (its mean and mean
        square, weight 0.9 to the past); a round missed (resumed) starts the smoothing afresh."""
        if self.last_theta is not None and self.last_theta[0] == k - 1:
            moved = theta - self.last_theta[1]
            if self.drift is None:
                self.drift = (moved, torch.square(moved))
            else:
                self.drift[0].mul_(0.9).add_(moved, alpha=0.1)
                self.drift[1].mul_(0.9).addcmul_(moved, moved, value=0.1)
        self.last_theta = (k, theta.clone())

    def widening(self, ages: torch.Tensor) -> torch.Tensor:
        """How much the variance of each mean of a State ``ages`` rounds old (one row per
        neighbour) has grown since it was sent: a parameter that moves d a round, with mean m and
        variance v = E[d^2] - m^2, may have moved t m by a steady drift and by noise of variance
        t v: t^2 m^2 + t v (a Kalman filter's prediction step, velocity and noise)."""
        mean, square = (x[self.mu_at] for x in self.drift)
        steady = torch.square(mean)
        t = ages[:, None]
        return t * t * steady[None] + t * (square - steady).clamp(min=0)[None]

    def dual_step(self, th_i: torch.Tensor, th_j: torch.Tensor, z: torch.Tensor, a: torch.Tensor | None) -> torch.Tensor:
        """A link's dual step. ``dinno`` (``a`` None): rho (theta_i - theta_j). ``ramen``:
        2 rho a (theta_i - z), RAMEN's 2 W_i W_j / (W_i + W_j) (theta_i - theta_j). ``sigma``:
        rho a (2 - a) (theta_i - theta_j), the same at both ends of the link up to sign
        (a_ji = 2 - a_ij), so that the two duals of a link cancel as DiNNO's do; an unbalanced
        pair would push the whole team off the data's optimum."""
        if a is None:
            return self.rho * (th_i - th_j)
        if self.s.consensus == "sigma":
            return self.rho * a * (2 - a) * (th_i - th_j)
        return 2 * self.rho * a * (th_i - z)

    def public_params(self, own: torch.Tensor) -> torch.Tensor:
        """The parameters the consensus terms take for this node: ``own``, or, where its States
        are compressed with error feedback, the copy its neighbours hold (as CHOCO-SGD): both ends
        of a link then compute its dual from the same two vectors, so the duals stay balanced,
        and what compression has not yet carried does not brake the team."""
        public = self.public()
        if public is None:
            return own
        return torch.from_numpy(np.array(public[: self.param_count], dtype=np.float32)).to(self.device)

    def forget(self, j: int) -> None:
        """Stop pulling towards neighbour ``j``'s last State (it went silent); its dual is kept
        aside, as for a lost link, for when it sends again."""
        self.known.pop(j, None)

    def forget_stale(self, k: int) -> None:
        """Drop the neighbours' States that arrived ``keep_for`` rounds or more before round ``k``
        (a neighbour gone, or a link that has stayed down)."""
        for j in [j for j, (arrived, _, _) in self.known.items() if k - arrived >= self.keep_for]:
            del self.known[j]

    def _primal(self, k: int, fresh) -> None:
        """A dual step per link in ``fresh`` (the neighbours heard from this round: as UDON, never
        against an outdated State), then ``primal_iterations`` optimizer steps on the loss plus
        the consensus terms of the neighbours whose newest State is at most ``keep_for`` rounds old,
        their duals only while it is at most ``duals_for`` (sigma's memory pulls without them: a
        dual carried on between States braked the team, see the README)."""
        self.forget_stale(k)
        th_reg = a = duals = None
        if self.known:
            ids = sorted(self.known)
            thj = torch.stack([self.known[j][1] for j in ids])
            cj = torch.stack([self.known[j][2] for j in ids]) if self.counts is not None else None
            th_i = self.public_params(torch.nn.utils.parameters_to_vector(self.model.parameters()).detach())
            th_reg, a = self.targets(k, ids, th_i, thj, cj)
            for row, j in enumerate(ids):
                if j in fresh:
                    step = self.dual_step(th_i, thj[row], th_reg[row], None if a is None else a[row])
                    self.duals[j] = self.duals.get(j, torch.zeros_like(th_i)) + step
            heard = [j for j in ids if k - self.known[j][0] < self.duals_for]  # the links this node hears from
            duals = torch.stack([self.duals[j] for j in heard]).sum(0) if heard else torch.zeros_like(th_i)
        lr = float(self.lrs[min(k, len(self.lrs) - 1)])
        if self.optimizers is None:
            optimizers = self._optimizers(lr)
        else:
            optimizers = self.optimizers
            for opt in optimizers:
                for group in opt.param_groups:
                    group["lr"] = lr
        for _ in range(self.s.primal_iterations):
            for opt in optimizers:
                opt.zero_grad()
            if self.counts is None:
                loss = self.batch_loss()
            else:  # RAMEN counts the steps that gave each parameter a gradient from the data
                bce, loss = self.batch_terms()
                bce.backward()
                self.counts += torch.cat([(p.grad != 0).reshape(-1) for p in self.model.parameters()]).float()
            if th_reg is not None:
                th = torch.nn.utils.parameters_to_vector(self.model.parameters())
                extra = torch.dot(th, duals) + self.consensus_penalty(th, th_reg, a)
                loss = extra if loss is None else loss + extra
            if loss is not None:
                loss.backward()  # one backward of the sum: both groups' gradients before either step
            for opt in optimizers:
                opt.step()


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
                  min_weight: float, widen: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``sigma`` consensus: per neighbour, the target and weight of every parameter.

    For each Bayesian mean, the product of the two Gaussians N(mu_i, sigma_i^2) and
    N(mu_j, sigma_j^2) has its mean at the precision-weighted midpoint
    z = mu_i + s (mu_j - mu_i), s = sigma_i^2 / (sigma_i^2 + sigma_j^2), which this node
    approaches with weight a = 2 s, clamped to [min_weight, 2 - min_weight] (1 where they are
    equally sure, as DiNNO; towards 2 where this node is the less sure).

    ``widen`` (one row per neighbour, one column per mean; None: every State is this round's):
    an outdated State tells where the neighbour's mean was, not where it is, so its variance is
    sigma_j^2 + w, w growing with its age (:meth:`DinnoNode.widening`). Its pull
    weakens with age and has no floor. Every other parameter (rho itself, the sine layer, the
    output layer) is pulled towards DiNNO's midpoint with weight 1, or for an outdated State
    with the mean of how much the widening weakened that neighbour's pulls on its means."""
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
    z = th_i + share * (thj - th_i)
    a = 2 * share
    a[:, mu_at] = torch.maximum(a[:, mu_at], floor).clamp(max=2 - min_weight)
    return z, a


def ramen_targets(th_i: torch.Tensor, c_i: torch.Tensor, thj: torch.Tensor, cj: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """``ramen`` consensus (RAMEN, Zhao et al. RSS 2025, ``scaling_AUQ_CADMM``): each side's
    weight W = p c + q maps its gradient count c linearly onto [rho / 1000, rho]; the target is
    the W-weighted midpoint and the pull is W / rho (penalty W_i (theta - z)^2, dual step
    2 W_i W_j / (W_i + W_j) (theta_i - theta_j)). RAMEN takes p and q from the range of the two
    sides' summed counts, which works for its hash grid, where many counts are 0; a dense
    network's counts are all far from 0, and that scaling then gives negative weights (and a
    target that runs off to infinity): here the range is that of both sides' counts. Counts
    alike everywhere give DiNNO's midpoint and weight."""
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


@torch.no_grad()
def validation_bce(model: torch.nn.Module, points: torch.Tensor, labels: torch.Tensor, batch: int = 65536) -> float:
    """Mean binary cross-entropy of ``model`` over a validation set (for a Bayesian or MC-dropout
    network, of its prediction: the mean of the sampled passes' probabilities, 10 passes)."""
    total = 0.0
    for s in range(0, len(points), batch):
        xy, y = points[s : s + batch], labels[s : s + batch]
        if isinstance(model, DropoutNet):  # one mask per pass for the batch, as its maps draw them
            plan = DropoutPlan(model, 10, torch.Generator(device=xy.device).manual_seed(s))
            p = torch.cat([torch.sigmoid(plan.logits(xy[c : c + 4096])).mean(0) for c in range(0, len(xy), 4096)])
            total += float(F.binary_cross_entropy(p.clamp(1e-7, 1 - 1e-7), y, reduction="sum"))
        elif isinstance(model, BayesNet):
            with model.noise(seed=s):
                p = torch.stack([model(xy) for _ in range(10)]).mean(0).clamp(1e-7, 1 - 1e-7)
            total += float(F.binary_cross_entropy(p, y, reduction="sum"))
        else:
            total += float(F.binary_cross_entropy_with_logits(model.logits(xy), y, reduction="sum"))
    return total / max(len(points), 1)


def consensus_error(theta_i: np.ndarray, peers: dict[int, np.ndarray]) -> float:
    """DiNNO's consensus metric for one node: mean distance between its unit-normalised
    parameter vector and its neighbours' (0 with no neighbours)."""
    if not peers:
        return 0.0
    a = theta_i / max(np.linalg.norm(theta_i), 1e-12)
    return float(np.mean([np.linalg.norm(a - p / max(np.linalg.norm(p), 1e-12)) for p in peers.values()]))


def self_weight(weights: dict[int, float], node: int, peers: dict[int, np.ndarray]) -> float:
    """A node's mixing weight for a round: its own, plus that of every neighbour absent from it."""
    return weights[node] + sum(w for j, w in weights.items() if j != node and j not in peers)


class DsgdNode(LocalNode):
    """DiNNO's DSGD baseline: mix with the neighbours by Metropolis weights, then one gradient
    step of size ``lrs[k]`` at the mixed parameters. (DiNNO's single-process loop mixes in
    place, so later nodes see earlier nodes' new values; here every node mixes round-k values,
    as independent processes must.)"""

    def __init__(self, model, points, labels, settings, seed, weights: dict[int, float], node: int, bounds=None):
        super().__init__(model, points, labels, settings, seed, bounds)
        self.weights, self.node = weights, node

    def update(self, k: int, theta_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        self.begin_round(k)
        own = self_weight(self.weights, self.node, peers)  # an absent neighbour's weight stays home
        mixed = own * torch.as_tensor(theta_i, device=self.device)
        for j, th in peers.items():
            mixed = mixed + self.weights[j] * torch.as_tensor(th, device=self.device)
        set_flat(self.model, mixed)
        g = self.gradient()
        set_flat(self.model, mixed - float(self.lrs[min(k, len(self.lrs) - 1)]) * g)
        return self.state()


class DsgtNode(LocalNode):
    """DiNNO's DSGT baseline (gradient tracking): the State carries [theta, y]; per round
    theta <- W_ii theta - alpha y_i + sum_j W_ij theta_j, then y <- W_ii y_i + sum_j W_ij y_j
    + g(theta) - g_old, with y and g_old starting at the gradient at theta_0."""

    def __init__(self, model, points, labels, settings, seed, weights: dict[int, float], node: int, bounds=None):
        super().__init__(model, points, labels, settings, seed, bounds)
        self.weights, self.node = weights, node
        self.n = sum(p.numel() for p in model.parameters())
        self.g_old = self.gradient()
        self.y = self.g_old.clone()

    def checkpoint(self) -> dict:
        return {**super().checkpoint(), "y": self.y.cpu(), "g_old": self.g_old.cpu()}

    def restore(self, doc: dict) -> None:
        super().restore(doc)
        self.y, self.g_old = doc["y"].to(self.device), doc["g_old"].to(self.device)

    def state_size(self) -> int:
        return 2 * self.n  # theta and its tracker

    def state(self) -> np.ndarray:
        return flatten_into([*self.model.parameters(), self.y], self.new_state(self.state_size()))


    def update(self, k: int, state_i: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        self.begin_round(k)
        n, w = self.n, self.weights
        own = torch.as_tensor(state_i, device=self.device)
        alpha = float(self.lrs[min(k, len(self.lrs) - 1)])
        w_own = self_weight(w, self.node, peers)
        theta = w_own * own[:n] - alpha * own[n:]
        y = w_own * own[n:]
        for j, st in peers.items():
            other = torch.as_tensor(st, device=self.device)
            theta = theta + w[j] * other[:n]
            y = y + w[j] * other[n:]
        set_flat(self.model, theta)
        g = self.gradient()
        self.y = y + g - self.g_old
        self.g_old = g
        return self.state()


