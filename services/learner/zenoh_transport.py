"""Algorithm 1's link over Zenoh: State and RoundComplete on each learner's own keys.

A node publishes on ``learners/<id>/state`` and ``learners/<id>/round-complete`` and
subscribes to exactly its neighbours' keys; a State whose parameter vector has another length
than this node's model, or a payload larger than twice its own State (:func:`state_bytes_limit`),
is refused (counted, logged once). At most ``inbox_limit`` messages
wait from any one neighbour (:class:`~swarmmap.services.learner.transport.Inbox`): a flood
beyond that is dropped, counted and logged once. The neighbours' ``exchange`` liveliness
tokens tell the exchange when one has left.

No copies of a vector beyond Zenoh's own: the node writes its State into a
:class:`~swarmmap.shared.wire.protocol.StateFrame` (:meth:`ZenohTransport.new_state`), which is sent
as it is, and a neighbour's State reaches Algorithm 1 as a read-only view of the received
payload. A :class:`~swarmmap.services.learner.codec.StateCodec` makes it Algorithm 1's transport.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from swarmmap.services.learner.transport import Delivery, Inbox
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.codec import StateFrame, encode_state
from swarmmap.shared.wire.protocol import MAX_COVERAGE_BYTES, ProtocolError, RoundComplete, State, StateBody

log = logging.getLogger("learner")


def state_bytes_limit(state_size: int) -> int:
    """The largest State payload a node of ``state_size`` values takes: twice its float32 State
    (a top-k State of every value carries an index beside each), its coverage bits and a header."""
    return 8 * state_size + MAX_COVERAGE_BYTES + 65536


class ZenohTransport:
    """One learner's end of Algorithm 1 over a :class:`~swarmmap.shared.wire.bus.Bus` (a Link).
    States of another size than ``state_size`` are refused."""

    def __init__(self, bus: Bus, node: int, neighbours: set[int], state_size: int, inbox_limit: int = 64):
        self.bus = bus
        self.node = node
        self.run = bus.keys.run
        self.inbox: Inbox[Delivery] = Inbox(inbox_limit)
        self._lost: set[int] = set()
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()  # a frame is stamped and sent as one step
        self.state_pub = bus.publisher(bus.keys.state(node))
        self.complete_pub = bus.publisher(bus.keys.round_complete(node))

        def check(msg: State) -> None:
            if msg.vector_size != state_size:
                raise ProtocolError("shape", f"a State of {msg.vector_size} values, this node's States have {state_size}")

        for j in sorted(neighbours):
            bus.subscribe(bus.keys.state(j), State, self._on_state, check=check, max_bytes=state_bytes_limit(state_size))
            bus.subscribe(bus.keys.round_complete(j), RoundComplete, self._on_complete)

        def on_alive(ident: str, alive: bool) -> None:
            if ident.isdigit() and int(ident) in neighbours:
                with self._lock:
                    (self._lost.discard if alive else self._lost.add)(int(ident))

        bus.watch_alive("exchange", on_alive)

    def _on_state(self, msg: State) -> None:
        self._queue(Delivery("state", msg.sender, msg.round, msg))

    def _on_complete(self, msg: RoundComplete) -> None:
        self._queue(Delivery("complete", msg.sender, msg.round))

    def _queue(self, msg: Delivery) -> None:
        if not self.inbox.put(msg) and self.inbox.dropped[msg.sender] == 1:
            log.warning("node %d: neighbour %d has %d messages waiting; dropping its further ones until this node "
                        "catches up (a flood? counted in the inbox)", self.node, msg.sender, self.inbox.per_sender)

    def new_state(self, n: int) -> np.ndarray:
        """A vector for the node to write its next State into: the payload it will be sent in."""
        return StateFrame.new(self.run, self.node, n)

    def send_state(self, round: int, params: np.ndarray) -> None:
        frame = StateFrame.of(params)
        if frame is None or frame.run != self.run or frame.sender != self.node:
            self.state_pub.put_bytes(encode_state(self.run, self.node, round, params))
            return
        with self._send_lock:
            self.state_pub.put_bytes(frame.stamp(round))

    def send_body(self, round: int, body: StateBody) -> None:
        """A State of another encoding (:mod:`~swarmmap.shared.wire.compression`), or with a position or coverage."""
        self.state_pub.put(body.state(self.run, self.node, round))

    def send_round_complete(self, round: int) -> None:
        self.complete_pub.put(RoundComplete(run=self.run, sender=self.node, round=round))

    def send_raw(self, kind: str, payload: bytes) -> None:
        """``payload`` as it is on this node's ``state`` or ``complete`` key (a hostile member's bombs)."""
        (self.state_pub if kind == "state" else self.complete_pub).put_bytes(payload)

    def receive(self, timeout: float) -> Delivery | None:
        return self.inbox.get(timeout)

    def lost_peers(self) -> set[int]:
        with self._lock:
            return set(self._lost)
