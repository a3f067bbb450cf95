"""The in-memory hub's end that speaks the wire codec: the reference run's links.

Every message is encoded to its bytes as over Zenoh, decoded and validated by each receiver
(a payload the codec refuses is counted in :attr:`MemoryLink.refused`), and its bytes counted
on the hub, so that the in-process run sends what the Zenoh run sends.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from swarmmap.services.learner.transport import Delivery, Envelope, Kind, MemoryHub, plain_vector
from swarmmap.shared.wire.codec import decode, encode, encode_state
from swarmmap.shared.wire.protocol import ProtocolError, RoundComplete, State, StateBody


class MemoryLink:
    """One node's end of a :class:`MemoryHub` that speaks the wire codec."""

    def __init__(self, hub: MemoryHub, node: int):
        if hub.run is None:
            raise ValueError("a MemoryHub speaks the wire codec only with a run id (MemoryHub(..., run=...))")
        self.hub, self.node = hub, node
        self.refused: Counter[str] = Counter()  # payloads the codec refused

    new_state = staticmethod(plain_vector)

    def _send(self, kind: Kind, round: int, payload: bytes) -> None:
        self.hub.deliver(self.node, (kind, payload), Envelope(kind, self.node, round), len(payload))

    def send_state(self, round: int, params: np.ndarray) -> None:
        self._send("state", round, encode_state(self.hub.run, self.node, round, params))

    def send_body(self, round: int, body: StateBody) -> None:
        self._send("state", round, encode(body.state(self.hub.run, self.node, round)))

    def send_round_complete(self, round: int) -> None:
        self._send("complete", round, encode(RoundComplete(run=self.hub.run, sender=self.node, round=round)))

    @property
    def run(self) -> str:
        return self.hub.run

    def send_raw(self, kind: Kind, payload: bytes) -> None:
        """``payload`` as it is, as a ``state`` or ``complete`` message (a hostile member's bombs)."""
        self._send(kind, 0, payload)

    def receive(self, timeout: float) -> Delivery | None:
        item = self.hub.take(self.node, timeout)
        if item is None:
            return None
        kind, payload = item
        self.hub.bytes_received[self.node] += len(payload)
        try:
            if kind == "complete":
                msg = decode(payload, RoundComplete, run=self.hub.run)
                return Delivery("complete", msg.sender, msg.round)
            state = decode(payload, State, run=self.hub.run)
            return Delivery("state", state.sender, state.round, state)
        except ProtocolError as exc:
            self.refused[exc.reason] += 1
            return None

    def lost_peers(self) -> set[int]:
        return self.hub.lost - {self.node}

    def wire_bytes(self) -> tuple[int, int]:
        """Bytes this node sent and received on Algorithm 1's links."""
        return self.hub.bytes_sent[self.node], self.hub.bytes_received[self.node]
