"""Injected faults on Algorithm 1's links: loss, duplication, delay and reordering.

:class:`FaultyTransport` wraps any link or transport of :mod:`~swarmmap.services.learner.transport`
(Zenoh's, the in-memory hub's ends) and applies ``faults`` (``FaultSettings``) to the messages
that reach this node from its neighbours, per link ``[sender, receiver]``: each message is lost
on its own, or (``per_round``) a link is up or down for a whole round, both ways. A learner uses
it when the run's ``faults`` section asks for any (tests, ``bench/``, experiments on poor
links); by default it is not there at all.
"""

from __future__ import annotations

import heapq
import itertools
import time

import numpy as np

from swarmmap.services.learner.transport import Delivery, Envelope, Link, Transport
from swarmmap.shared.run.config import FaultSettings
from swarmmap.shared.wire.protocol import StateBody

Message = Envelope | Delivery


def any_faults(faults: FaultSettings) -> bool:
    return faults.link_success < 1 or faults.duplicate > 0 or faults.delay_s > 0


class FaultyTransport:
    """A link (or transport) whose incoming messages are lost, duplicated and delayed (hence reordered)."""

    def __init__(self, inner: Link | Transport, node: int, faults: FaultSettings):
        self.inner, self.node, self.f = inner, node, faults
        self.rng = np.random.default_rng([faults.seed, node])
        self.links = {tuple(link) for link in faults.links}
        self.pending: list[tuple[float, int, Message]] = []  # (due, order, message)
        self.order = itertools.count()
        self.dropped = self.duplicated = 0

    def new_state(self, n: int) -> np.ndarray:
        return self.inner.new_state(n)

    def send_state(self, round: int, params: np.ndarray) -> None:
        self.inner.send_state(round, params)

    def send_body(self, round: int, body: StateBody) -> None:
        self.inner.send_body(round, body)

    def send_round_complete(self, round: int) -> None:
        self.inner.send_round_complete(round)

    def lost_peers(self) -> set[int]:
        return self.inner.lost_peers()

    def _faulty(self, sender: int) -> bool:
        return not self.links or (sender, self.node) in self.links

    def _admit(self, msg: Message) -> None:
        if not self._faulty(msg.sender):
            heapq.heappush(self.pending, (0.0, next(self.order), msg))
            return
        up = self._link_up(msg) if self.f.per_round else self.rng.random() < self.f.link_success
        if not up:
            self.dropped += 1
            return
        copies = 2 if self.rng.random() < self.f.duplicate else 1
        self.duplicated += copies - 1
        for _ in range(copies):
            due = time.monotonic() + (self.rng.uniform(0, self.f.delay_s) if self.f.delay_s > 0 else 0.0)
            heapq.heappush(self.pending, (due, next(self.order), msg))

    def _link_up(self, msg: Message) -> bool:
        """Whether the link between ``msg.sender`` and this node is up in the message's round: one
        draw per link and round, the same at both ends (a radio link down for a round carries
        nothing either way, resends included)."""
        a, b = sorted((msg.sender, self.node))
        return np.random.default_rng([self.f.seed, a, b, msg.round]).random() < self.f.link_success

    def receive(self, timeout: float) -> Message | None:
        """The next message due, waiting up to ``timeout`` seconds (0: what has arrived)."""
        deadline = time.monotonic() + timeout
        while True:
            now = time.monotonic()
            if self.pending and self.pending[0][0] <= now:
                return heapq.heappop(self.pending)[2]
            wait = max(0.0, deadline - now if not self.pending else min(deadline, self.pending[0][0]) - now)
            msg = self.inner.receive(timeout=wait)  # (with no time left, still what the inner link holds)
            if msg is not None:
                self._admit(msg)
            elif time.monotonic() >= deadline:
                return None
