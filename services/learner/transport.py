"""How a node talks to its neighbours: the two seams below Algorithm 1, and the in-memory hub.

Two layers, each a protocol:

- :class:`Transport` is what Algorithm 1 and the clock mode use: send a State (a float32
  vector) or a RoundComplete for a round, receive the next :class:`Envelope` (a neighbour's
  vector, never an encoded message), learn who has left, and get the buffer the node writes its
  next State into (:meth:`Transport.new_state`, the payload it is sent from, where the link has one).
- :class:`Link` is the wire below it: it sends a State's vector or an encoded
  :class:`~swarmmap.shared.wire.protocol.StateBody` and delivers what arrives as a :class:`Delivery`
  (the received :class:`~swarmmap.shared.wire.protocol.State`, still encoded). A
  :class:`~swarmmap.services.learner.codec.StateCodec` turns a Link into a Transport;
  :class:`~swarmmap.services.learner.faults.FaultyTransport` sits between the two.

Implementations: :class:`~swarmmap.services.learner.zenoh_transport.ZenohTransport` (a Link over
Zenoh) and :class:`MemoryHub` (in process: :meth:`MemoryHub.transport` passes vectors as objects,
for Algorithm 1's tests; a :class:`~swarmmap.services.learner.memory_link.MemoryLink` speaks the
wire codec, for the reference run). Nothing here imports the wire protocol: Algorithm 1 depends
on this module only.
"""

from __future__ import annotations

import queue
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, Literal, Protocol, TypeVar

import numpy as np

if TYPE_CHECKING:
    from swarmmap.shared.wire.protocol import State, StateBody

Kind = Literal["state", "complete"]


@dataclass(frozen=True)
class Envelope:
    """One Algorithm 1 message as a node takes it: a State's vector, or none for a RoundComplete.
    ``exact``: the vector is what the sender sent, and the same again when it sends it again (not a
    compressed chain's, which a resend after a replay re-encodes)."""

    kind: Kind
    sender: int
    round: int
    params: np.ndarray | None = None
    exact: bool = True


@dataclass(frozen=True)
class Delivery:
    """One message as a link receives it: a State still encoded (its vector rebuilt by a StateCodec)."""

    kind: Kind
    sender: int
    round: int
    state: State | None = None


class Transport(Protocol):
    """Algorithm 1's view of its links: vectors in, vectors out."""

    def new_state(self, n: int) -> np.ndarray:
        """A float32 vector of ``n`` values for the node's next State (the payload it is sent from, where there is one)."""

    def send_state(self, round: int, params: np.ndarray) -> None:
        """Send ``State(round)`` with ``params`` to every neighbour."""

    def send_round_complete(self, round: int) -> None:
        """Send ``RoundComplete(round)`` to every neighbour."""

    def receive(self, timeout: float) -> Envelope | None:
        """The next message from a neighbour, waiting up to ``timeout`` seconds (0: only what has arrived)."""

    def lost_peers(self) -> set[int]:
        """The neighbours that have left (their liveliness tokens vanished)."""


class Link(Protocol):
    """The wire below a Transport: encoded States in, encoded States out."""

    def new_state(self, n: int) -> np.ndarray: ...

    def send_state(self, round: int, params: np.ndarray) -> None:
        """Send a plain float32 State (the fast path)."""

    def send_body(self, round: int, body: StateBody) -> None:
        """Send a State of another encoding, or with a position or coverage."""

    def send_round_complete(self, round: int) -> None: ...

    def receive(self, timeout: float) -> Delivery | None: ...

    def lost_peers(self) -> set[int]: ...


M = TypeVar("M", Envelope, Delivery)


class Inbox(Generic[M]):
    """Received messages in arrival order, at most ``per_sender`` of them waiting from any one
    neighbour: beyond that, a sender's new messages are dropped and counted (:attr:`dropped`).
    A member of the run that floods its links then costs bounded memory, and an honest
    neighbour's messages, which Algorithm 1 resends while they are missing, are never held
    back by another's flood."""

    def __init__(self, per_sender: int = 64):
        self.per_sender = per_sender
        self._queue: queue.SimpleQueue[M] = queue.SimpleQueue()
        self._held: Counter[int] = Counter()
        self.dropped: Counter[int] = Counter()
        self._lock = threading.Lock()

    def put(self, msg: M) -> bool:
        """Queue ``msg``; False (dropped) when its sender already has ``per_sender`` waiting."""
        with self._lock:
            if self._held[msg.sender] >= self.per_sender:
                self.dropped[msg.sender] += 1
                return False
            self._held[msg.sender] += 1
        self._queue.put(msg)
        return True

    def get(self, timeout: float) -> M | None:
        """The oldest message, waiting up to ``timeout`` seconds for one."""
        try:
            msg = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        with self._lock:
            self._held[msg.sender] -= 1
        return msg


def plain_vector(n: int) -> np.ndarray:
    """A State buffer of a link that has no payload to write into: a fresh float32 vector."""
    return np.empty(n, np.float32)


class MemoryHub:
    """In-process links for the reference run and tests: one queue per node.

    :meth:`transport` passes vectors as objects (Algorithm 1's tests, vectors of any dtype);
    :class:`~swarmmap.services.learner.memory_link.MemoryLink` (on a hub made with ``run``, a run
    id) sends every message through the wire codec, as over Zenoh: encoded to its bytes, decoded and validated by each receiver, and its
    bytes counted (``bytes_sent`` per sender, ``bytes_received`` per receiver).

    ``delay(sender, receiver, message) -> seconds`` may hold a message back, which reorders
    deliveries the way a network can.
    """

    def __init__(self, graph: dict[int, set[int]], delay: Callable[[int, int, Envelope], float] | None = None,
                 run: str | None = None):
        self.graph = graph
        self.delay = delay
        self.run = run
        self.queues: dict[int, queue.Queue] = {i: queue.Queue() for i in graph}
        self.timers: list[threading.Timer] = []
        self.lost: set[int] = set()  # nodes that have left (as their liveliness tokens would say)
        self.bytes_sent: Counter[int] = Counter()
        self.bytes_received: Counter[int] = Counter()

    def transport(self, node: int) -> MemoryTransport:
        """Node ``node``'s end, passing vectors as objects."""
        return MemoryTransport(self, node)

    def deliver(self, sender: int, item, header: Envelope, size: int = 0) -> None:
        """Queue ``item`` (an Envelope, or a message's bytes) for every neighbour of ``sender``;
        ``header`` says what it is, for the delay."""
        self.bytes_sent[sender] += size
        for j in self.graph[sender]:
            wait = self.delay(sender, j, header) if self.delay else 0.0
            if wait > 0:
                timer = threading.Timer(wait, self.queues[j].put, args=(item,))
                timer.daemon = True
                self.timers.append(timer)
                timer.start()
            else:
                self.queues[j].put(item)

    def take(self, node: int, timeout: float):
        """The next item queued for ``node``, or None after ``timeout`` seconds."""
        try:
            return self.queues[node].get(timeout=timeout)
        except queue.Empty:
            return None


class MemoryTransport:
    """One node's end of a :class:`MemoryHub`, vectors passed as objects (copied when sent)."""

    def __init__(self, hub: MemoryHub, node: int):
        self.hub, self.node = hub, node

    new_state = staticmethod(plain_vector)

    def send_state(self, round: int, params: np.ndarray) -> None:
        env = Envelope("state", self.node, round, np.array(params, copy=True))
        self.hub.deliver(self.node, env, env)

    def send_round_complete(self, round: int) -> None:
        env = Envelope("complete", self.node, round)
        self.hub.deliver(self.node, env, env)

    def receive(self, timeout: float) -> Envelope | None:
        return self.hub.take(self.node, timeout)

    def lost_peers(self) -> set[int]:
        return self.hub.lost - {self.node}
