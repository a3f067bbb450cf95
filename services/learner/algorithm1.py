"""The paper's Algorithm 1 (Peers State Exchange) as a round state machine, free of any transport.

A node sends ``State(round)``, waits for every neighbour's State of that round, runs its node
update, sends ``RoundComplete(round)`` and finishes the round (:meth:`Algorithm1.finish_round`,
the paper's FINISHROUND) once every neighbour is complete or a neighbour's State of a later
round shows that it has moved on. Finishing sends ``State(round + 1)`` with the updated
parameters. Messages come in through :meth:`Algorithm1.on_state` and
:meth:`Algorithm1.on_complete`; :meth:`Algorithm1.run` drives the machine over a
:class:`~swarmmap.services.learner.transport.Transport`.

Beyond the paper's listing: messages are buffered per round, so an early State is kept for its
round and a late or duplicate one is ignored (rounds never mix); a node never finishes a round
before its own update; this round's messages are sent again after ``resend_after`` seconds
without progress, then after twice as long, up to RESEND_BACKOFF times (receivers ignore
duplicates; a link too slow for a round's messages is not flooded with their copies). Robots come and go
(:mod:`~swarmmap.services.learner.membership`): a neighbour that left or went silent is left
out (a neighbour is heard only when it moves forward: its first State of a round that this node
takes, or its RoundComplete of a round whose State it took, whatever round this node is at; a State of a far-future round or one
it already sent is no word from it) and the round finishes with the neighbours the node has; it is taken back when it sends a
State of the round at hand; a node that restarts behind its team replays the rounds it lost or
catches up to the team's round: from its own parameters, or, when it is more than REUNION_ROUNDS
rounds behind (it waited alone through a partition), from its neighbours' States of that round
(their median), its own data staying in its loss. Only a node left with no neighbour at all for ``peer_timeout``
seconds stops, with :class:`~swarmmap.services.learner.exchange.PeerFailure`. A node with no
neighbours in its graph trains alone.

Poor links (``round_wait`` > 0): a node that has been ``round_wait`` seconds in a round runs its
update with the neighbours' States that have arrived (none, if none has) and finishes the round
without waiting for the RoundCompletes still missing. The team's rounds then drift apart: a
neighbour's State of another round is kept as its newest word and given to the update of a
round that got none of its own from it; nothing is replayed. The neighbours a round went on
without are missing from it only (``stats.missed``); nobody is left out for it.

This module imports no wire protocol, codec, bus or Zenoh: it sees vectors and rounds only.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from swarmmap.services.learner.exchange import (
    CHECK_EVERY_S,
    ROUNDS_AHEAD,
    ExchangeRules,
    ExchangeStats,
    NodeUpdate,
    Rejoin,
    RoundCheck,
    StateCheck,
    refuse,
)
from swarmmap.services.learner.membership import (
    RESEND_BACKOFF,
    REUNION_ROUNDS,
    LateStates,
    Membership,
    Replay,
    RoundBuffer,
    round_states,
)
from swarmmap.services.learner.pace import Pace
from swarmmap.services.learner.transport import Envelope, Transport

log = logging.getLogger("learner")


class Algorithm1:
    """One node's rounds. ``update(round, state, {peer: state})`` is its NODEUPDATE; ``check(theirs,
    own)`` refuses a State on its own (``check_stale`` when its own parameters are rounds old),
    ``screen(own, {peer: state})`` the round's together; ``rejoin`` gives a jump's start."""

    def __init__(self, node_id: int, neighbours: set[int], update: NodeUpdate, transport: Transport,
                 rules: ExchangeRules = ExchangeRules(), *, check: StateCheck | None = None, screen: RoundCheck | None = None,
                 check_stale: StateCheck | None = None, rejoin: Rejoin | None = None, stats: ExchangeStats | None = None,
                 stop: threading.Event | None = None):
        self.node_id, self.neighbours, self.update, self.transport, self.rules = node_id, set(neighbours), update, transport, rules
        self.check, self.screen, self.rejoin, self.stop = check, screen, rejoin, stop
        self.check_stale = check_stale if check_stale is not None else check
        self.stats = stats if stats is not None else ExchangeStats()
        self.begin(np.zeros(0, np.float32), 0, 0, False)

    def begin(self, state: np.ndarray, rounds: int, start_round: int, resumed: bool) -> None:
        """Start afresh at round ``start_round`` of ``rounds`` from ``state``."""
        self.members = Membership(self.node_id, self.neighbours, self.rules, self.stats, clip=getattr(self.check, "clip", None))
        self.replay = Replay(self.node_id, self.rules.keep_rounds, self.rules.resend_after, self.stats)
        self.late, self.buf = LateStates(), RoundBuffer()
        self.rnd, self.rounds, self.updated, self.joining = start_round, rounds, False, resumed
        self.round_started = time.monotonic()
        self.state = self.round_state = state  # round_state: what State(rnd) carries, the round's start (resent as such)

    def advance(self) -> bool:
        """Update and finish rounds as far as the buffered messages allow; whether anything moved."""
        moved = False
        while self.rnd < self.rounds and (self.node_update() | self.finish_round()):
            moved = True
        return moved

    def node_update(self) -> bool:
        """NODEUPDATE once every neighbour of the round sent its State (or its wait is over), then RoundComplete."""
        peers, active = self.buf.states[self.rnd], self.members.active
        ready = (active or not self.neighbours) and active <= peers.keys()
        if self.updated or not (ready or self.wait_over()):
            return False
        busy_since = time.monotonic()
        used = round_states(self.members, self.screen, self.state, peers, self.late, self.rnd)
        self.state = self.update(self.rnd, self.state, dict(sorted(used.items())))
        self.stats.update_s += self.members.progress.paused(time.monotonic() - busy_since)
        self.updated = True
        self.send_complete()
        return True

    def finish_round(self) -> bool:
        """The paper's FINISHROUND: once the node has updated and every neighbour of the round is
        complete, or one has moved on (its State of the next round is here), go to the next
        round and send its State. Returns whether it did."""
        moved_on = any(j in self.buf.states[self.rnd + 1] for j in self.neighbours)
        if not (self.updated and (self.members.active <= self.buf.complete[self.rnd] or moved_on or self.wait_over())):
            return False
        self.joining = self.joining and not self.members.active
        self.buf.drop(self.rnd)
        self.rnd += 1
        self.updated = False
        self.round_started = time.monotonic()
        self.stats.rounds_done += 1
        self.members.next_round(self.rnd, lambda j: self.buf.held(j, self.rnd) is not None)
        self.round_state = self.state
        self.send_state()
        return True

    def wait_over(self) -> bool:
        """Poor links: this round has waited ``round_wait`` seconds for messages."""
        return self.rules.round_wait > 0 and time.monotonic() - self.round_started >= self.rules.round_wait

    def on_message(self, msg: Envelope, now: float) -> None:
        """Route one neighbour's message: poor links' other rounds, a neighbour behind, or this node's
        rounds. A neighbour that says two different things for one round is hostile: left out for good."""
        if msg.sender in self.members.banned:
            return
        if msg.kind == "complete":  # (of any round: a node that moved on still hears a neighbour finish)
            self.members.progress.completed(msg.sender, msg.round, now)
        if msg.kind == "state" and self.buf.held(msg.sender, msg.round) is not None:  # the first State of a round counts
            if msg.exact and self.members.judge(msg, self.check, self.state):  # a second, different, plausible one: a liar
                self.members.equivocates(msg, self.buf, self.late, self.rnd)
            return
        newest = self.replay.seen(msg.sender, msg.round) if msg.kind == "state" else False
        if self.rules.round_wait > 0 and not self.joining and not self.rnd <= msg.round <= self.rnd + ROUNDS_AHEAD:
            if self.late.offer(msg, lambda m: self.members.judge(m, self.check, self.state)):  # (a newer State it takes)
                self.members.progress.heard_from(msg.sender, now)
        elif msg.round < self.rnd:  # a neighbour behind (restarted): send it the States it needs again
            if newest:  # (it computes its rounds anew: what it sent before it died is not held against it)
                self.buf.forget_sender(msg.sender)
                self.replay.answer(msg.sender, msg.round, self.rnd, self.transport, now)
        elif msg.kind == "complete":
            self.on_complete(msg, now)
        else:
            self.on_state(msg, now)

    def on_complete(self, msg: Envelope, now: float) -> None:
        """A neighbour's RoundComplete of this round or one ahead (word from it only where it
        completes a State taken: :meth:`Progress.completed`; one that completes rounds without
        sending its State is silent)."""
        if msg.round <= self.rnd + ROUNDS_AHEAD:
            self.buf.complete[msg.round].add(msg.sender)

    def on_state(self, msg: Envelope, now: float) -> None:
        """A State of this round or a later one: kept for its round, a reason to catch up, or refused."""
        j, r = msg.sender, msg.round
        keep = self.rules.keep_rounds
        # Left behind (slow to start, starved of CPU): stuck here longer than the neighbours wait for
        # anyone while they are further ahead than they can replay: catch up rather than wait.
        left_behind = (now - self.round_started > self.rules.silent_after
                       and self.rnd + max(keep, ROUNDS_AHEAD) < r <= self.rounds)
        jump = ((self.joining and not self.updated and self.rnd + keep < r <= self.rounds) or left_behind
                ) and self.members.vouched(self.replay.newest, r)
        if r > self.rnd + ROUNDS_AHEAD and not jump:
            if not (self.joining and r <= self.rnd + keep):  # (those are the replay's, coming)
                refuse(self.stats, self.node_id, msg, f"round {r} while this node is at round {self.rnd}", "far-future")
            return
        stale = (self.joining and not self.updated) or left_behind  # own parameters rounds old: judged more loosely
        if not self.members.judge(msg, self.check_stale if stale else self.check, self.state):
            return
        self.members.progress.took_state(j, r, now)  # a State that moves it forward: its first of a round, taken
        if jump:
            self.catch_up(msg, now, left_behind)
            return
        self.buf.states[r][j] = msg.params
        if j not in self.members.active:
            self.members.came_back(j, self.rnd, now_round=r == self.rnd and not self.updated)

    def catch_up(self, msg: Envelope, now: float, left_behind: bool) -> None:
        """The team is too far ahead to replay: jump to its round, from ``rejoin``'s State."""
        j = msg.sender
        log.info("node %d: neighbour %d is at round %d; catching up from round %d%s", self.node_id, j, msg.round, self.rnd,
                 f" (left behind for {now - self.round_started:.0f} s)" if left_behind else "")
        behind = msg.round - self.rnd
        self.buf.keep_from(msg.round)
        self.rnd, self.updated, self.round_started = msg.round, False, now
        self.buf.states[self.rnd][j] = msg.params
        self.state = jump_start(self.node_id, self.state, dict(self.buf.states[self.rnd]), behind, self.rnd, self.rejoin)
        self.round_state = self.state
        self.members.jumped(j, set(self.buf.states[self.rnd]), self.rnd)
        self.stats.caught_up += 1
        self.send_state()

    def send_state(self) -> None:
        t0 = time.perf_counter()
        self.replay.remember(self.rnd, self.round_state)
        self.transport.send_state(self.rnd, self.round_state)
        self.stats.send_s += time.perf_counter() - t0

    def send_complete(self) -> None:
        t0 = time.perf_counter()
        self.transport.send_round_complete(self.rnd)
        self.stats.send_s += time.perf_counter() - t0


def jump_start(node_id: int, own: np.ndarray, peers: dict[int, np.ndarray], behind: int, rnd: int,
               rejoin: Rejoin | None) -> np.ndarray:
    """The State a node that catches up ``behind`` rounds to round ``rnd`` goes on from: more than
    REUNION_ROUNDS behind (it waited alone through a partition), its own parameters are of a much
    earlier stage of the training than its team's: the neighbours' States of the round (their
    median), its own data staying in its loss; else ``rejoin``'s (its own)."""
    if behind > REUNION_ROUNDS:
        log.info("node %d: %d rounds behind its team, it goes on from %s of round %d (its own data stays in its loss)",
                 node_id, behind, f"the median of neighbours {sorted(peers)}' States" if len(peers) > 1
                 else f"neighbour {next(iter(peers))}'s State", rnd)
        return np.median(np.stack(list(peers.values())), axis=0).astype(own.dtype)
    return rejoin(own, peers) if rejoin is not None else own


class RoundLoop:
    """Drives an :class:`Algorithm1` over its transport: listens for messages, looks every
    CHECK_EVERY_S for neighbours gone or silent, resends the round's messages after
    ``resend_after`` seconds without progress, notes each round's wait and training (``pace``),
    and waits for the final States."""

    def __init__(self, machine: Algorithm1, pace: Pace | None = None):
        self.m = machine
        self.pace = pace if pace is not None else Pace(machine.node_id)
        self.last_progress = time.monotonic()
        self.resend_wait = machine.rules.resend_after  # doubles after each resend of a round, up to RESEND_BACKOFF x
        self.round_mark = (0, 0.0, 0.0)  # a round, and the wait and update seconds when it began

    def run(self, state: np.ndarray, rounds: int, start_round: int = 0, resumed: bool = False) -> np.ndarray:
        """Run rounds ``start_round .. rounds - 1`` from ``state``; return the final state. After
        the last round the node waits up to ``linger`` seconds for its neighbours' final States
        (``stats.final_peers``), which also gives its own last messages time to reach them."""
        m = self.m
        m.begin(state, rounds, start_round, resumed)
        m.send_state()
        last_check = self.last_progress = time.monotonic()
        self.round_mark = (m.rnd, m.stats.wait_s, m.stats.update_s)
        while m.rnd < rounds:
            if m.stop is not None and m.stop.is_set():
                raise InterruptedError(f"node {m.node_id} stopped at round {m.rnd}")
            if m.advance():
                self.progress()
            if m.rnd >= rounds:
                break
            now = time.monotonic()
            if now - last_check >= CHECK_EVERY_S:  # whatever arrives, look at who is gone or silent
                last_check = now
                self.housekeeping(now)
                continue  # the neighbours left out may let the round advance
            self.listen()
        m.stats.final_peers = self.final_states()
        return m.state

    def progress(self) -> None:
        """Rounds moved: note each finished round's pace."""
        m = self.m
        self.last_progress = time.monotonic()
        self.resend_wait = m.rules.resend_after
        rnd, wait, busy = self.round_mark
        if m.rnd == rnd + 1:  # (a jump is no round's pace)
            self.pace.round_done(m.rnd, m.stats.wait_s - wait, m.stats.update_s - busy)
        if m.rnd != rnd:
            self.round_mark = (m.rnd, m.stats.wait_s, m.stats.update_s)

    def housekeeping(self, now: float) -> None:
        """Leave out the neighbours this round waits on that are gone or silent; resend this
        round's messages after ``resend_wait`` seconds without progress (``resend_after``, doubled
        after each resend of the round, up to RESEND_BACKOFF times it)."""
        m = self.m
        lost = m.transport.lost_peers()
        m.replay.forget(lost)
        m.members.check(m.buf.still_needed(m.members.active, m.rnd, m.updated), lost, m.rnd, now)
        if now - self.last_progress > self.resend_wait:
            m.send_state()
            if m.updated:
                m.send_complete()
            m.stats.resends += 1
            self.last_progress = now
            self.resend_wait = min(2 * self.resend_wait, RESEND_BACKOFF * m.rules.resend_after)

    def listen(self) -> None:
        """Wait for the next message (at most until the next check, or the end of the round's wait)."""
        m = self.m
        t0 = time.perf_counter()
        timeout = CHECK_EVERY_S
        if m.rules.round_wait > 0:  # wake when this round's wait for States or RoundCompletes is over
            timeout = min(timeout, max(0.005, m.round_started + m.rules.round_wait - time.monotonic()))
        msg = m.transport.receive(timeout=timeout)
        m.stats.wait_s += time.perf_counter() - t0
        if msg is not None and msg.sender in m.neighbours:
            m.on_message(msg, time.monotonic())

    def final_states(self) -> dict[int, np.ndarray]:
        """Wait up to ``linger`` seconds for the active neighbours' States of the last round."""
        m = self.m
        deadline = time.monotonic() + m.rules.linger
        final = m.buf.states[m.rounds]
        while not m.members.active <= final.keys() and time.monotonic() < deadline:
            msg = m.transport.receive(timeout=max(0.0, min(0.2, deadline - time.monotonic())))
            if (msg is not None and msg.kind == "state" and msg.sender in m.neighbours - m.members.banned
                    and msg.round == m.rounds and msg.sender not in final and m.members.judge(msg, m.check, m.state)):
                final[msg.sender] = msg.params
        return dict(final)
