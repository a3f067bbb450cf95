"""What Algorithm 1's States look like on the wire: their rounds and their encoding.

:class:`StateCodec` turns a :class:`~swarmmap.services.learner.transport.Link` (Zenoh's, the
in-memory hub's, a faulty one) into the :class:`~swarmmap.services.learner.transport.Transport`
Algorithm 1 takes: vectors in, vectors out. It

- numbers States by training round: with ``learner.exchange_every`` = E, Algorithm 1's round c
  is training rounds cE .. cE + E - 1 and its State travels as round cE, so observers and logs
  see training rounds whatever E is;
- compresses States (``learner.compression``, :mod:`~swarmmap.shared.wire.compression`) and rebuilds
  the vectors of the States it receives, whatever encoding each sender chose. It sits outside
  the fault layer, so a State the harness loses is lost to the rebuilding too;
- on a dynamic disk graph (``radius``), stamps each State with its robot's position and ignores
  the messages of neighbours farther than ``radius`` (their link is out of range: a round with
  ``learner.round_wait_s`` goes on without them);
- with a :class:`~swarmmap.shared.world.unseen.Coverage` (``learner.share_coverage``), stamps each
  State with the cells its node knows some robot covers, and offers what the States it
  receives say to it (merged once the node is past their round; transitively, the team's
  coverage spreads along the graph).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import numpy as np

from swarmmap.services.learner.transport import Delivery, Envelope, Link
from swarmmap.shared.wire.compression import Decompressor, Encoder, Plain
from swarmmap.shared.wire.protocol import StateBody, Tensor
from swarmmap.shared.world.unseen import Coverage

log = logging.getLogger("learner")


class StateCodec:
    """One node's States, encoded and numbered for the wire, over ``inner``."""

    def __init__(self, inner: Link, node: int, compressor: Encoder | None = None, every: int = 1,
                 radius: float | None = None, position: Callable[[], tuple[float, float] | None] | None = None,
                 coverage: Coverage | None = None):
        self.inner, self.node, self.every = inner, node, every
        self.coverage = coverage
        self.compressor = compressor if compressor is not None else Plain()
        self.radius, self.position = radius, position
        self.out_of_range: dict[int, bool] = {}  # per sender: was its newest State from out of range
        self.ignored = 0  # messages from neighbours out of range
        self.decompressor = Decompressor()
        self.cached: tuple[int, int, StateBody] | None = None  # (round, compressor seq, body) of the newest State sent
        self.logged: set[tuple[str, int]] = set()
        self.unusable = 0  # States received that could not be rebuilt or were off the exchange rounds

    def send_state(self, round: int, params: np.ndarray, whole: bool = False) -> None:
        """Send the State of ``round``; ``whole``: one that stands alone (a compressed chain's key
        frame: the final State said again after the run, for a neighbour that restarted since)."""
        wire = round * self.every
        where = self.position() if self.position is not None else None
        c = self.compressor
        if c.plain and where is None and self.coverage is None:
            self.inner.send_state(wire, params)  # the fast path: the frame the node wrote its parameters into
            return
        held = self.cached is not None and self.cached[0] == round and self.cached[1] == c.seq
        if held and not (whole and self.cached[2].base is not None):
            body = self.cached[2]  # the same State again: the same bytes (receivers ignore duplicates)
        else:
            # A State of an older round (sent again to a neighbour that restarted) goes whole: it
            # starts the replicas again for whoever missed what came before; the next ones add to it.
            body = c.body(params, keyframe=whole or (self.cached is not None and round < self.cached[0]))
            self.cached = (round, c.seq, body)
        if where is not None:
            body = dataclasses.replace(body, position=[float(where[0]), float(where[1])])
        if self.coverage is not None:
            body = dataclasses.replace(body, coverage=Tensor.of(self.coverage.packed(), "|u1"))
        self.inner.send_body(wire, body)

    def new_state(self, n: int) -> np.ndarray:
        """The link's payload buffer where a plain State is sent as it is; else a fresh vector."""
        if self.compressor.plain and self.position is None and self.coverage is None:
            return self.inner.new_state(n)
        return np.empty(n, np.float32)

    def in_range(self, msg: Delivery) -> bool:
        """Whether a message comes from within ``radius`` (a State by its position; a RoundComplete
        by its sender's newest State). Without positions to compare, it does."""
        if msg.state is not None and msg.state.position is not None:
            here = self.position() if self.position is not None else None
            far = here is not None and math.dist(here, msg.state.position) > self.radius
            self.out_of_range[msg.sender] = far
            if far and msg.state.seq is not None:
                self.decompressor.vector(msg.state)  # a chain (its key frames too) is followed even out of range
            return not far
        return not self.out_of_range.get(msg.sender, False)

    def send_round_complete(self, round: int) -> None:
        self.inner.send_round_complete(round * self.every)

    def lost_peers(self) -> set[int]:
        return self.inner.lost_peers()

    def _once(self, key: tuple[str, int], text: str) -> None:
        self.unusable += 1
        self.logged_once(key, text)

    def offer_coverage(self, sender: int, round: int, bits: np.ndarray) -> None:
        try:
            self.coverage.offer(round, bits)
        except ValueError as exc:  # another map or margin: its cells are not ours
            self.logged_once(("coverage", sender), f"node {sender}'s coverage ignored: {exc} (another map or "
                                                    f"learner.unseen_margin_m?)")

    def logged_once(self, key: tuple[str, int], text: str) -> None:
        if key not in self.logged:
            self.logged.add(key)
            log.warning("node %d: %s (not logged again)", self.node, text)

    def receive(self, timeout: float) -> Envelope | None:
        """The next message as Algorithm 1 takes it: an exchange round's, in range, its vector rebuilt."""
        msg = self.inner.receive(timeout)
        if msg is None:
            return None
        if msg.round % self.every:
            self._once(("rounds", msg.sender), f"node {msg.sender} sent a {msg.kind} for round {msg.round}, not an exchange "
                                                f"round (every {self.every}): does it run with another learner.exchange_every?")
            return None
        if self.radius is not None and not self.in_range(msg):
            self.ignored += 1
            return None
        params = None if msg.state is None else self.vector(msg)
        if msg.state is not None and params is None:
            return None
        exact = msg.state is None or msg.state.seq is None  # (a chain's vector depends on what came before it)
        return Envelope(msg.kind, msg.sender, msg.round // self.every, params, exact)

    def vector(self, msg: Delivery) -> np.ndarray | None:
        """A received State's vector: a plain one's as a read-only view of its payload (no copy),
        any other rebuilt by the decompressor (None, logged once, when its chain is broken)."""
        state = msg.state
        if self.coverage is not None and state.coverage is not None:
            self.offer_coverage(msg.sender, msg.round, state.coverage.numpy())
        if state.plain:
            return state.params.numpy()
        vec = self.decompressor.vector(state)
        if vec is None:
            self._once(("chain", msg.sender), self.decompressor.why)
        return vec
