"""The training rounds inside Algorithm 1's rounds, and the round at which each thing happens.

With ``learner.exchange_every`` = E, Algorithm 1's round c is training rounds cE .. cE + E - 1:
the first with the neighbours' States of the exchange, the others against them as they were
(:meth:`~swarmmap.services.learner.node.Node.local_update`). On a clock
(``learner.exchange_every_s``) every training round takes the States that came since the last.
Each training round first reports (every ``eval_every`` rounds, and at least every REPORT_S
seconds: a team on slow links shows it is moving) and, online, takes the newest
window of scans; each Algorithm 1 round whose training rounds pass a multiple of
``checkpoint_every`` starts with a checkpoint. A round whose parameters are no longer finite
stops the learner (:class:`~swarmmap.services.learner.errors.LearnerError`, status 6).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext

import numpy as np

from swarmmap.services.learner.errors import LearnerError
from swarmmap.services.learner.node import Node
from swarmmap.services.learner.settings import ScheduleSettings
from swarmmap.shared.wire.codec import all_finite

Report = Callable[[int, np.ndarray, dict[int, np.ndarray]], None]  # report(round, own State, the peers' States)
Save = Callable[[int, np.ndarray], None]  # save(Algorithm 1 round, the State it starts from)
Window = Callable[[int], tuple[np.ndarray, np.ndarray] | None]  # round k's training points where they change (online)
REPORT_S = 60.0  # a round's Metrics at least this often, whatever eval_every (the recorder's stall watch lives on them)


class SubRounds:
    """One robot's training rounds around its node. ``start_round`` (an Algorithm 1 round) is the
    one the learner resumed from: its checkpoint is on disk already. ``slots`` is held while an
    Algorithm 1 round trains (at most N learners of a host at once)."""

    def __init__(self, node: Node, schedule: ScheduleSettings, report: Report, *, save: Save | None = None,
                 window: Window | None = None, start_round: int = 0, slots: AbstractContextManager | None = None,
                 name: str = "node", diverged: str = ""):
        self.node, self.s, self.report, self.save, self.window = node, schedule, report, save, window
        self.start_round, self.slots, self.name, self.diverged = start_round, slots or nullcontext(), name, diverged
        self.latest: dict[int, np.ndarray] = {}  # on a clock: each neighbour's newest State
        self.compute_s = 0.0
        self.reported_at = time.monotonic()

    def exchange_update(self, c: int, theta: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """Algorithm 1's round ``c``: its training rounds, the first with the neighbours' States."""
        e = self.s.exchange_every
        # Its data first, outside the compute slot: an exploring learner may wait for its robot's drive there.
        data = {k: self.window(k) for k in range(c * e, (c + 1) * e)} if self.window is not None else {}
        with self.slots:  # (its neighbours' next States cannot come before it sends its own: it waits without one)
            self.checkpoint_if_due(c, theta)
            for k in range(c * e, (c + 1) * e):
                theta = self.train_round(k, theta, peers, exchange=k == c * e, data=data.get(k))
        return theta

    def clock_update(self, k: int, theta: np.ndarray, fresh: dict[int, np.ndarray]) -> np.ndarray:
        """Training round ``k`` on a clock: an exchange round for the neighbours whose States came
        since the last round, if any."""
        self.latest.update(fresh)
        self.checkpoint_if_due(k, theta)  # (on a clock exchange_every is 1: Algorithm 1's rounds are training rounds)
        data = self.window(k) if self.window is not None else None
        return self.train_round(k, theta, self.latest, exchange=bool(fresh), fresh=fresh, data=data)

    def forget(self, j: int) -> None:
        """Neighbour ``j`` went silent (on a clock): the update stops pulling towards its last State."""
        self.latest.pop(j, None)
        self.node.forget(j)

    def checkpoint_if_due(self, c: int, theta: np.ndarray) -> None:
        """What Algorithm 1's round ``c`` starts from, when its training rounds pass a multiple of
        ``checkpoint_every`` (not in the round this learner resumed from: that one is on disk)."""
        every, e = self.s.checkpoint_every, self.s.exchange_every
        if every and (c * e) % every < e and c != self.start_round and self.save is not None:
            self.save(c, theta)

    def train_round(self, k: int, theta: np.ndarray, peers: dict[int, np.ndarray], exchange: bool,
                    fresh: dict[int, np.ndarray] | None = None, data: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Training round ``k``: its new training ``data`` where there is some (DiNNO's sliding window,
        exploration's legs), the report every ``eval_every`` rounds or REPORT_S seconds (consensus
        error against ``peers``), then the node's update with the neighbours' States that came
        (``fresh``, default ``peers``) where ``exchange``, else against the States it holds."""
        if data is not None:
            self.node.set_data(*data)
        if k % self.s.eval_every == 0 or time.monotonic() - self.reported_at >= REPORT_S:
            self.report(k, theta, peers)
            self.reported_at = time.monotonic()
        t0 = time.perf_counter()
        theta = self.node.update(k, theta, peers if fresh is None else fresh) if exchange else self.node.local_update(k, theta)
        self.compute_s += time.perf_counter() - t0
        if not all_finite(self.node.layout.params_of(theta)):
            raise LearnerError(f"{self.name}: training diverged in round {k}: its parameters are no longer finite "
                               f"({self.diverged})", 6)
        return theta
