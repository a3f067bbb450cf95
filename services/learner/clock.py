"""Exchange on a clock (``learner.exchange_every_s``): robots whose radios talk every few seconds.

A node runs its training rounds back to back and never waits for anyone. Before a round it
sends its State when ``every_s`` seconds have passed since it last did (and before its first
round), and takes every State that has arrived meanwhile; the update gets the newest of each
neighbour that came since the last round (none in most rounds: it then trains against the
States it already holds). No RoundComplete, no resends: a State lost is lost, the next one
comes ``every_s`` seconds later. The team's round numbers drift apart; a State older than one
already taken from the same neighbour (reordered) is ignored.

States are screened as in Algorithm 1, except that the robots train apart between exchanges: a
State passes when it is plausible against this node's parameters or against another neighbour's
newest State taken (never the sender's own earlier one: a State may not vouch for the next). A
neighbour that sends two different States for one round is hostile and never heard again. A neighbour silent for ``silent_after`` seconds
is forgotten (``forget(j)``: the update stops pulling towards its last State) until it sends
again; a node never fails for want of neighbours. After the last round the node sends its final
State (round ``rounds``) and waits up to ``linger`` seconds for its neighbours' final States
(``stats.final_peers``, with the newest State of any that has not finished by then).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from swarmmap.services.learner.exchange import ExchangeRules, ExchangeStats, NodeUpdate, StateCheck, refuse
from swarmmap.services.learner.transport import Envelope, Transport

log = logging.getLogger("learner")
DRAIN_PER_ROUND = 10_000  # messages taken from the inbox before a round at most (a flood cannot stall it)


class ClockExchange:
    """One node's training rounds with States exchanged every ``every_s`` seconds."""

    def __init__(self, node_id: int, neighbours: set[int], update: NodeUpdate, transport: Transport, every_s: float,
                 rules: ExchangeRules = ExchangeRules(), *, check: StateCheck | None = None,
                 check_stale: StateCheck | None = None, forget: Callable[[int], None] | None = None,
                 stats: ExchangeStats | None = None, stop: threading.Event | None = None):
        self.node_id, self.neighbours, self.update, self.transport = node_id, set(neighbours), update, transport
        self.every_s, self.rules, self.check, self.forget, self.stop = every_s, rules, check, forget, stop
        self.check_stale = check_stale if check_stale is not None else check
        self.stats = stats if stats is not None else ExchangeStats()
        self.newest: dict[int, tuple[int, np.ndarray]] = {}  # each neighbour's newest State taken: (round, vector)
        self.heard: dict[int, float] = {}
        self.forgotten: set[int] = set()
        self.banned: set[int] = set()  # said two different things for one round
        self.state = np.zeros(0, np.float32)

    def run(self, state: np.ndarray, rounds: int, start_round: int = 0) -> np.ndarray:
        """Training rounds ``start_round .. rounds - 1`` from ``state``; the final state."""
        self.state, last_sent = state, -math.inf
        for k in range(start_round, rounds):
            if self.stop is not None and self.stop.is_set():
                raise InterruptedError(f"node {self.node_id} stopped at round {k}")
            now = time.monotonic()
            if now - last_sent >= self.every_s:
                t0 = time.perf_counter()
                self.transport.send_state(k, self.state)
                self.stats.send_s += time.perf_counter() - t0
                last_sent = now
            fresh = self.drain()
            self.forget_silent(now, k)
            self.state = self.update(k, self.state, dict(sorted(fresh.items())))
            self.stats.rounds_done += 1
        self.transport.send_state(rounds, self.state)
        self.linger(rounds)
        return self.state

    def drain(self) -> dict[int, np.ndarray]:
        """Every message that has arrived; the newest State of each neighbour that passes."""
        t0 = time.perf_counter()
        arrived: dict[int, Envelope] = {}  # the newest of each neighbour: only those are judged (a flood costs no checks)
        for _ in range(DRAIN_PER_ROUND):
            msg = self.transport.receive(timeout=0.0)
            if msg is None:
                break
            was = arrived.get(msg.sender)
            if was is not None and self.equivocates(was, msg):
                continue
            if was is None or msg.round >= was.round:
                arrived[msg.sender] = msg
        for j in self.banned & arrived.keys():
            del arrived[j]
        fresh: dict[int, np.ndarray] = {}
        for msg in arrived.values():
            self.take(msg, fresh, time.monotonic())
        self.stats.wait_s += time.perf_counter() - t0
        return fresh

    def take(self, msg: Envelope, into: dict[int, np.ndarray], now: float) -> None:
        """Keep a neighbour's State (in ``into`` too) if it is news and plausible."""
        j = msg.sender
        if msg.kind != "state" or j not in self.neighbours or j in self.banned or msg.round < self.newest.get(j, (-1, None))[0]:
            return  # RoundCompletes (a node on round-based exchange), strangers, reordered older States
        why = self.judge(j, msg.params)
        if why is not None:
            refuse(self.stats, self.node_id, msg, why, "implausible")  # (why, against its own parameters)
            return
        if j in self.forgotten:
            self.forgotten.discard(j)
            self.stats.rejoined += 1
            log.info("node %d: neighbour %d heard again at its round %d", self.node_id, j, msg.round)
        self.newest[j] = (msg.round, msg.params)
        self.heard[j] = now
        into[j] = msg.params

    def equivocates(self, was: Envelope, msg: Envelope) -> bool:
        """Whether ``msg`` is a second, plausible and different State of the same sender and round
        as ``was`` (both arrived since the last round): the sender is then banned for the run."""
        j = msg.sender
        if (msg.kind != "state" or was.kind != "state" or was.round != msg.round or not (msg.exact and was.exact)
                or np.array_equal(was.params, msg.params) or self.judge(j, msg.params) is not None):
            return False
        self.banned.add(j)
        self.forgotten.discard(j)
        self.heard.pop(j, None)
        self.newest.pop(j, None)
        self.stats.refused["equivocation"] += 1
        self.stats.refused_from[j] += 1
        log.warning("node %d: neighbour %d sent two different States for its round %d; it is left out for the rest of "
                    "the run", self.node_id, j, msg.round)
        if self.forget is not None:
            self.forget(j)
        return True

    def judge(self, j: int, theirs: np.ndarray) -> str | None:
        """Why ``theirs`` (from ``j``) is refused against every reference (this node's parameters
        and the other neighbours' newest), or None when one of them finds it plausible. Before
        the node has taken any State (it starts, or resumed behind its team), against its own
        parameters more loosely (``check_stale``)."""
        if self.check is None:
            return None
        others = [v for k, (_, v) in self.newest.items() if k != j]
        refs = [(self.check, self.state)] + [(self.check, v) for v in others] if self.newest else [(self.check_stale, self.state)]
        first = None
        for check, ref in refs:
            why = check(theirs, ref)
            if why is None:
                return None
            first = first or why
        return first

    def forget_silent(self, now: float, k: int) -> None:
        """Forget the neighbours silent for ``silent_after`` seconds."""
        for j in [j for j, t in self.heard.items() if j not in self.forgotten and now - t > self.rules.silent_after]:
            self.forgotten.add(j)
            self.stats.left_out += 1
            log.warning("node %d: neighbour %d has been silent for %.0f s; round %d goes on without its last State",
                        self.node_id, j, now - self.heard[j], k)
            if self.forget is not None:
                self.forget(j)

    def linger(self, rounds: int) -> None:
        """Wait up to ``linger`` seconds for the neighbours' final States."""
        deadline = time.monotonic() + self.rules.linger
        while (any(self.newest.get(j, (-1, None))[0] < rounds for j in self.neighbours - self.forgotten - self.banned)
               and time.monotonic() < deadline):
            msg = self.transport.receive(timeout=max(0.0, min(0.2, deadline - time.monotonic())))
            if msg is not None:
                self.take(msg, {}, time.monotonic())
        self.stats.final_peers = {j: v for j, (_, v) in sorted(self.newest.items()) if j not in self.forgotten}
