"""The paper's Algorithm 1 (Peers State Exchange) against a small transport interface.

A node sends ``State(round)``, waits for every neighbour's State of that round, runs its node
update, sends ``RoundComplete(round)`` and finishes the round once every neighbour is complete
or a neighbour's State of a later round shows that it has moved on (the paper's FINISHROUND on
a future State). Finishing sends ``State(round + 1)`` with the updated parameters.

Beyond the paper's listing: messages are buffered per round, so an early State is kept for its
round and a late or duplicate one is ignored (rounds never mix); a node never finishes a round
before its own update; this round's messages are sent again after ``resend_after`` seconds
without progress (receivers ignore duplicates), and a neighbour that left (its liveliness token
vanished) or stayed silent for ``peer_timeout`` seconds while still needed stops the node with
:class:`PeerFailure` naming it. A node with no neighbours trains alone.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

log = logging.getLogger("learner")


@dataclass(frozen=True)
class Envelope:
    """One received Algorithm 1 message."""

    kind: Literal["state", "complete"]
    sender: int
    round: int
    params: np.ndarray | None = None


class Transport(Protocol):
    """How a node talks to its neighbours: Zenoh in deployment, memory in the reference run."""

    def send_state(self, round: int, params: np.ndarray) -> None: ...

    def send_round_complete(self, round: int) -> None: ...

    def receive(self, timeout: float) -> Envelope | None: ...

    def lost_peers(self) -> set[int]: ...


class PeerFailure(RuntimeError):
    """A neighbour this node still needs is gone or silent."""


@dataclass
class ExchangeStats:
    """Time spent waiting for peers and sending, per node, accumulated over rounds; States refused."""

    wait_s: float = 0.0
    send_s: float = 0.0
    rounds_done: int = 0
    resends: int = 0
    final_peers: dict[int, np.ndarray] = field(default_factory=dict)
    refused: Counter[str] = field(default_factory=Counter)
    logged: set[tuple[str, int]] = field(default_factory=set)


# A State of a round further ahead than this cannot be needed yet (a neighbour is at most one
# round ahead of a node it waits for); it is refused, so that memory stays bounded.
ROUNDS_AHEAD = 2
StateCheck = Callable[[np.ndarray, np.ndarray], "str | None"]


def implausible(theirs: np.ndarray, own: np.ndarray, max_distance: float) -> str | None:
    """Why a neighbour's parameters cannot come from an honest node, or None.

    Honest neighbours start from the same initialisation and consensus keeps them close, so
    parameters that are constant (e.g. all zero) or farther from this node's own than
    ``max_distance`` times the norm of its own are refused."""
    if theirs.shape != own.shape:
        return f"{theirs.size} parameters, expected {own.size}"
    if not np.isfinite(theirs).all():
        return "non-finite parameters"
    if theirs.size > 1 and np.ptp(theirs) == 0:
        return f"constant parameters ({float(theirs[0]):g} everywhere)"
    scale = float(np.linalg.norm(own))
    distance = float(np.linalg.norm(theirs.astype(np.float64) - own))
    if scale > 0 and distance > max_distance * scale:
        return f"parameters {distance / scale:.2f} x the own parameters' norm away (limit {max_distance:g})"
    return None


@dataclass
class _Rounds:
    states: dict[int, dict[int, np.ndarray]] = field(default_factory=lambda: defaultdict(dict))
    complete: dict[int, set[int]] = field(default_factory=lambda: defaultdict(set))


NodeUpdate = Callable[[int, np.ndarray, dict[int, np.ndarray]], np.ndarray]


def run_algorithm1(node_id: int, neighbours: set[int], max_rounds: int, state: np.ndarray,
                   node_update: NodeUpdate, transport: Transport, *, start_round: int = 0,
                   stats: ExchangeStats | None = None, stop: threading.Event | None = None,
                   peer_timeout: float = 120.0, resend_after: float = 2.0, linger: float = 5.0,
                   check_state: StateCheck | None = None) -> np.ndarray:
    """Run rounds ``start_round .. max_rounds - 1``; return the final state.

    ``node_update(round, state, {peer: peer_state})`` is the algorithm (DiNNO's, here); it sees
    exactly the neighbours' States of ``round``. After the last round the node waits up to
    ``linger`` seconds for its neighbours' final States (kept in ``stats.final_peers``), which
    also gives its own last messages time to reach them before the caller closes the transport.
    ``check_state(theirs, own)`` may refuse a neighbour's State (it returns why); refused States,
    and States more than ROUNDS_AHEAD rounds ahead, are counted in ``stats.refused`` and the
    round goes on without them.
    """
    stats = stats if stats is not None else ExchangeStats()
    buf = _Rounds()
    rnd = start_round
    updated = False

    def send_state() -> None:
        t0 = time.perf_counter()
        transport.send_state(rnd, state)
        stats.send_s += time.perf_counter() - t0

    def send_complete() -> None:
        t0 = time.perf_counter()
        transport.send_round_complete(rnd)
        stats.send_s += time.perf_counter() - t0

    send_state()
    last_progress = time.monotonic()
    last_resend = last_progress
    while rnd < max_rounds:
        if stop is not None and stop.is_set():
            raise InterruptedError(f"node {node_id} stopped at round {rnd}")
        # Advance as far as the buffered messages allow.
        progressed = True
        while progressed and rnd < max_rounds:
            progressed = False
            peers = buf.states[rnd]
            if not updated and neighbours <= peers.keys():
                state = node_update(rnd, state, {j: peers[j] for j in sorted(neighbours)})
                updated = True
                send_complete()
                progressed = True
            moved_on = any(j in buf.states[rnd + 1] for j in neighbours)
            if updated and (neighbours <= buf.complete[rnd] or moved_on):
                buf.states.pop(rnd, None)
                buf.complete.pop(rnd, None)
                rnd += 1
                updated = False
                stats.rounds_done += 1
                send_state()
                progressed = True
            if progressed:
                last_progress = last_resend = time.monotonic()
        if rnd >= max_rounds:
            break
        t0 = time.perf_counter()
        msg = transport.receive(timeout=min(resend_after, 0.5))
        stats.wait_s += time.perf_counter() - t0
        if msg is not None:
            if msg.sender in neighbours and msg.round >= rnd:
                if msg.round > rnd + ROUNDS_AHEAD:
                    refuse(stats, node_id, msg, f"round {msg.round} while this node is at round {rnd}", "far-future")
                elif msg.kind == "complete":
                    buf.complete[msg.round].add(msg.sender)
                elif msg.sender not in buf.states[msg.round]:  # the first State of a round counts
                    why = check_state(msg.params, state) if check_state is not None else None
                    if why is None:
                        buf.states[msg.round][msg.sender] = msg.params
                    else:
                        refuse(stats, node_id, msg, why, "implausible")
            continue
        now = time.monotonic()
        needed = _still_needed(neighbours, buf, rnd, updated)
        gone = needed & transport.lost_peers()
        if gone:
            raise PeerFailure(f"node {node_id}: neighbour(s) {sorted(gone)} left during round {rnd} "
                              f"(their liveliness token vanished) before sending what round {rnd} needs")
        if now - last_progress > peer_timeout:
            raise PeerFailure(f"node {node_id}: no progress in round {rnd} for {peer_timeout:.0f} s; "
                              f"still waiting for neighbour(s) {sorted(needed)}")
        if now - last_resend > resend_after:
            send_state()
            if updated:
                send_complete()
            stats.resends += 1
            last_resend = now
    deadline = time.monotonic() + linger
    final = buf.states[max_rounds]
    while not neighbours <= final.keys() and time.monotonic() < deadline:
        msg = transport.receive(timeout=max(0.0, min(0.2, deadline - time.monotonic())))
        if msg is not None and msg.kind == "state" and msg.sender in neighbours and msg.round == max_rounds:
            final[msg.sender] = msg.params
    stats.final_peers = dict(final)
    return state


def refuse(stats: ExchangeStats, node_id: int, msg: Envelope, why: str, reason: str) -> None:
    """Count a refused State; log the first of each reason per sender."""
    stats.refused[reason] += 1
    if (reason, msg.sender) not in stats.logged:
        stats.logged.add((reason, msg.sender))
        log.warning("node %d: refused the %s of node %d for round %d: %s (further ones are only counted)", node_id,
                    msg.kind, msg.sender, msg.round, why)


def _still_needed(neighbours: set[int], buf: _Rounds, rnd: int, updated: bool) -> set[int]:
    if not updated:
        return neighbours - buf.states[rnd].keys()
    if any(j in buf.states[rnd + 1] for j in neighbours):
        return set()
    return neighbours - buf.complete[rnd]


class MemoryHub:
    """In-process transport for the reference run and tests: one queue per node.

    ``delay(sender, receiver, envelope) -> seconds`` may hold a message back, which reorders
    deliveries the way a network can.
    """

    def __init__(self, graph: dict[int, set[int]],
                 delay: Callable[[int, int, Envelope], float] | None = None):
        import queue

        self.graph = graph
        self.delay = delay
        self.queues = {i: queue.Queue() for i in graph}
        self.timers: list[threading.Timer] = []

    def transport(self, node: int) -> MemoryTransport:
        return MemoryTransport(self, node)

    def deliver(self, sender: int, env: Envelope) -> None:
        for j in self.graph[sender]:
            wait = self.delay(sender, j, env) if self.delay else 0.0
            if wait > 0:
                timer = threading.Timer(wait, self.queues[j].put, args=(env,))
                timer.daemon = True
                self.timers.append(timer)
                timer.start()
            else:
                self.queues[j].put(env)


class MemoryTransport:
    """One node's end of a :class:`MemoryHub`."""

    def __init__(self, hub: MemoryHub, node: int):
        self.hub = hub
        self.node = node

    def send_state(self, round: int, params: np.ndarray) -> None:
        self.hub.deliver(self.node, Envelope("state", self.node, round, np.array(params, copy=True)))

    def send_round_complete(self, round: int) -> None:
        self.hub.deliver(self.node, Envelope("complete", self.node, round))

    def receive(self, timeout: float) -> Envelope | None:
        import queue

        try:
            return self.hub.queues[self.node].get(timeout=timeout)
        except queue.Empty:
            return None

    def lost_peers(self) -> set[int]:
        return set()
