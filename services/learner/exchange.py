"""The paper's Algorithm 1 (Peers State Exchange) against a small transport interface.

A node sends ``State(round)``, waits for every neighbour's State of that round, runs its node
update, sends ``RoundComplete(round)`` and finishes the round once every neighbour is complete
or a neighbour's State of a later round shows that it has moved on (the paper's FINISHROUND on
a future State). Finishing sends ``State(round + 1)`` with the updated parameters.

Beyond the paper's listing: messages are buffered per round, so an early State is kept for its
round and a late or duplicate one is ignored (rounds never mix); a node never finishes a round
before its own update; this round's messages are sent again after ``resend_after`` seconds
without progress (receivers ignore duplicates). Robots come and go (the paper assumes they do
not): a neighbour that left (its liveliness token vanished) or went silent is left out and the
round finishes with the neighbours the node has; it is taken back when it sends a State of the
round at hand; a node that restarts behind its team catches up to the team's round. Only a
node left with no neighbour at all for ``peer_timeout`` seconds stops, with :class:`PeerFailure`.
A node with no neighbours in its graph trains alone.

:func:`run_timed` is the other way to exchange (``learner.exchange_every_s``): on a clock,
never waiting, taking the neighbours' States as they come.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from swarmmap.shared.protocol import ProtocolError, RoundComplete, State, decode, encode, encode_state

log = logging.getLogger("learner")


@dataclass(frozen=True)
class Envelope:
    """One received Algorithm 1 message."""

    kind: Literal["state", "complete"]
    sender: int
    round: int
    params: np.ndarray | State | None = None  # a State of another encoding until a StateCodec rebuilds its vector


class Inbox:
    """Received messages in arrival order, at most ``per_sender`` of them waiting from any one
    neighbour: beyond that, a sender's new messages are dropped and counted (:attr:`dropped`).
    A member of the run that floods its links then costs bounded memory, and an honest
    neighbour's messages, which Algorithm 1 resends while they are missing, are never held
    back by another's flood."""

    def __init__(self, per_sender: int = 64):
        self.per_sender = per_sender
        self._queue: queue.SimpleQueue[Envelope] = queue.SimpleQueue()
        self._held: Counter[int] = Counter()
        self.dropped: Counter[int] = Counter()
        self._lock = threading.Lock()

    def put(self, env: Envelope) -> bool:
        """Queue ``env``; False (dropped) when its sender already has ``per_sender`` waiting."""
        with self._lock:
            if self._held[env.sender] >= self.per_sender:
                self.dropped[env.sender] += 1
                return False
            self._held[env.sender] += 1
        self._queue.put(env)
        return True

    def get(self, timeout: float) -> Envelope | None:
        try:
            env = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        with self._lock:
            self._held[env.sender] -= 1
        return env


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
    left_out: int = 0  # times a neighbour was left out of a round (gone or silent)
    rejoined: int = 0  # times one came back
    caught_up: int = 0  # times this node jumped ahead to its team's round
    replayed: int = 0  # States sent again to neighbours that were behind
    missed: int = 0  # neighbours' States a round went on without (round_wait: poor links)


# A State of a round further ahead than this cannot be needed yet (a neighbour is at most one
# round ahead of a node it waits for); it is refused, so that memory stays bounded.
ROUNDS_AHEAD = 2
StateCheck = Callable[[np.ndarray, "np.ndarray | None"], "str | None"]
Rejoin = Callable[[np.ndarray, dict[int, np.ndarray]], np.ndarray]
CHECK_EVERY_S = 0.5  # how often a waiting node looks for neighbours gone or silent


def implausible(theirs: np.ndarray, own: np.ndarray | None, max_distance: float) -> str | None:
    """Why a neighbour's parameters cannot come from an honest node, or None.

    Honest neighbours start from the same initialisation and consensus keeps them close, so
    parameters that are constant (e.g. all zero) or farther from this node's own than
    ``max_distance`` times the norm of its own are refused. Without ``own`` (a node catching up
    with its team holds stale parameters) only the first test applies."""
    if own is not None and theirs.shape != own.shape:
        return f"{theirs.size} parameters, expected {own.size}"
    if not np.isfinite(theirs).all():
        return "non-finite parameters"
    if theirs.size > 1 and np.ptp(theirs) == 0:
        return f"constant parameters ({float(theirs[0]):g} everywhere)"
    if own is None:
        return None
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
                   check_state: StateCheck | None = None, silent_after: float = 30.0,
                   rejoin: Rejoin | None = None, resumed: bool = False, rejoin_wait: float = 0.0,
                   keep_rounds: int = 0, round_wait: float = 0.0) -> np.ndarray:
    """Run rounds ``start_round .. max_rounds - 1``; return the final state.

    ``node_update(round, state, {peer: peer_state})`` is the algorithm (DiNNO's, here); it sees
    exactly the States of ``round`` of the neighbours it has. After the last round the node
    waits up to ``linger`` seconds for its neighbours' final States (kept in
    ``stats.final_peers``), which also gives its own last messages time to reach them before the
    caller closes the transport. ``check_state(theirs, own)`` may refuse a neighbour's State (it
    returns why); refused States, and States more than ROUNDS_AHEAD rounds ahead, are counted in
    ``stats.refused`` and the round goes on without them.

    Robots come and go. A neighbour whose liveliness token vanished (and did not come back within
    ``rejoin_wait`` seconds, the time a launcher needs to restart it), or that stayed silent for
    ``silent_after`` seconds while this node waited on it, is left out: the round finishes with
    the neighbours the node has. It is taken back once it sends a State of the round at hand or
    a later one. Silence is counted while the node waits, not while it computes: a long update
    or evaluation (a big model, a starved CPU) does not make its neighbours look gone, whose
    States meanwhile wait in its inbox. A node ``resumed`` from a checkpoint may be behind its
    team. Each node keeps the States it sent in its last ``keep_rounds`` rounds and, when a
    neighbour sends a State of an older round, sends them again: the resumed node replays the
    rounds it lost with exactly the States its neighbours had (and comes back where it would have
    been). Further behind than that, it jumps: before it has finished a round with a neighbour, a plausible State more than
    ``keep_rounds`` rounds ahead makes it jump to that round, starting from
    ``rejoin(own_state, {peer: state})`` (default: its own state). So does a node left behind:
    one stuck in a round for longer than ``silent_after`` (its neighbours have left it out by
    then) that receives a State further ahead than they can replay. A node whose neighbours are
    all left out waits for one to come back, and fails (PeerFailure) when it has had none for
    ``peer_timeout`` seconds.

    Poor links (``round_wait`` > 0): a node that has been ``round_wait`` seconds in a round runs
    its update with the neighbours' States that have arrived (none, if none has) and finishes the
    round without waiting for the RoundCompletes still missing: a round waits at most
    ``round_wait`` seconds for messages. The team's rounds then drift apart: a neighbour's State
    of another round (behind, or further ahead than ROUNDS_AHEAD) is kept as its newest word and
    given to the update of a round that got none of its own from it; nothing is replayed, and
    such States are not refused. The neighbours a round went on without are missing from it only
    (``stats.missed``); nobody is left out for it. Where every message arrives in time, the
    rounds are Algorithm 1's.
    """
    stats = stats if stats is not None else ExchangeStats()
    buf = _Rounds()
    rnd = start_round
    updated = False
    active = set(neighbours)  # the neighbours this round waits for
    returning: set[int] = set()  # left out, but sent a State of this round or a later one: back next round
    joining = resumed  # may jump ahead to its team's round, until it finishes a round with a neighbour
    round_started = time.monotonic()  # when this node began its current round
    heard = dict.fromkeys(neighbours, time.monotonic())  # the last message from each neighbour
    refused_since: dict[int, float] = {}  # per neighbour: its first refused State since it last sent one this node took
    lost_since: dict[int, float] = {}
    alone_since: float | None = None

    round_state = state  # what State(rnd) carries: the parameters at the start of the round (resent as such)
    history: dict[int, np.ndarray] = {}  # the States of the last keep_rounds rounds, for neighbours that replay them
    replayed: dict[tuple[int, int], float] = {}
    newest: dict[int, int] = {}  # newest round of a State from each neighbour (forgotten when it leaves: it restarts)
    late: dict[int, tuple[int, np.ndarray]] = {}  # poor links: each neighbour's newest State of another round

    def send_state() -> None:
        t0 = time.perf_counter()
        history[rnd] = round_state
        for old in [r for r in history if r < rnd - keep_rounds]:
            del history[old]
        transport.send_state(rnd, round_state)
        stats.send_s += time.perf_counter() - t0

    def send_complete() -> None:
        t0 = time.perf_counter()
        transport.send_round_complete(rnd)
        stats.send_s += time.perf_counter() - t0

    def leave_out(j: int, why: str) -> None:
        active.discard(j)
        stats.left_out += 1
        log.warning("node %d: neighbour %d %s; round %d goes on without it", node_id, j, why, rnd)

    def wait_over() -> bool:
        """Poor links: this round has waited ``round_wait`` seconds for messages."""
        return round_wait > 0 and time.monotonic() - round_started >= round_wait

    def acceptable(msg: Envelope, own: np.ndarray | None) -> bool:
        """Whether a neighbour's State passes ``check_state``; a refused one is counted, and when
        the neighbour's refused States began is kept (it is left out if they go on)."""
        why = check_state(msg.params, own) if check_state is not None else None
        if why is None:
            refused_since.pop(msg.sender, None)
            return True
        refused_since.setdefault(msg.sender, time.monotonic())
        refuse(stats, node_id, msg, why, "implausible")
        return False

    def finish_round() -> bool:
        """The paper's FINISHROUND: once the node has updated and every neighbour of the round is
        complete, or one has moved on (its State of the next round is here), go to the next
        round and send its State. Returns whether it did."""
        nonlocal rnd, updated, joining, round_state, round_started
        moved_on = any(j in buf.states[rnd + 1] for j in neighbours)
        if not (updated and (active <= buf.complete[rnd] or moved_on or wait_over())):
            return False
        joining = joining and not active
        buf.states.pop(rnd, None)
        buf.complete.pop(rnd, None)
        rnd += 1
        updated = False
        round_started = time.monotonic()
        stats.rounds_done += 1
        if returning:
            log.info("node %d: neighbour(s) %s back from round %d", node_id, sorted(returning), rnd)
            active.update(returning)
            stats.rejoined += len(returning)
            returning.clear()
        round_state = state
        send_state()
        return True

    send_state()
    last_resend = last_check = time.monotonic()
    while rnd < max_rounds:
        if stop is not None and stop.is_set():
            raise InterruptedError(f"node {node_id} stopped at round {rnd}")
        # Advance as far as the buffered messages allow.
        progressed = True
        while progressed and rnd < max_rounds:
            progressed = False
            peers = buf.states[rnd]
            if not updated and (((active or not neighbours) and active <= peers.keys()) or wait_over()):
                busy_since = time.monotonic()
                used = {j: peers[j] for j in active & peers.keys()}
                for j in list(late):
                    if j in used and late[j][0] <= rnd:
                        del late[j]  # older than the State of this round
                    elif j in active and j not in used:
                        used[j] = late.pop(j)[1]  # this round's did not come: the newest of another round
                stats.missed += len(active) - len(used)
                state = node_update(rnd, state, dict(sorted(used.items())))
                busy = time.monotonic() - busy_since
                for j in heard:  # silence counts while this node listens, not while it computes
                    heard[j] += busy  # (what the neighbours sent meanwhile waits in its inbox)
                    if j in refused_since:
                        refused_since[j] += busy
                updated = True
                send_complete()
                progressed = True
            if finish_round():
                progressed = True
            if progressed:
                last_resend = time.monotonic()
        if rnd >= max_rounds:
            break
        now = time.monotonic()
        if now - last_check >= CHECK_EVERY_S:  # whatever arrives, look at who is gone or silent
            last_check = now
            # Leave out the neighbours this round waits on that are gone or silent.
            lost = transport.lost_peers()
            lost_since = {j: lost_since.get(j, now) for j in lost}
            for j in lost:
                newest.pop(j, None)
            for j in sorted(_still_needed(active, buf, rnd, updated)):
                if j in lost and now - lost_since[j] >= rejoin_wait:
                    leave_out(j, "left (its liveliness token vanished)" + (f" and is not back after {rejoin_wait:.0f} s"
                                                                            if rejoin_wait else ""))
                elif now - heard[j] > silent_after:
                    leave_out(j, f"has been silent for {now - heard[j]:.0f} s")
                elif not updated and now - refused_since.get(j, now) > silent_after:  # it talks, but only in refused States
                    leave_out(j, f"has sent only States this node refuses for {now - refused_since[j]:.0f} s")
            if neighbours and not active:
                alone_since = alone_since or now
                if now - alone_since > peer_timeout:
                    raise PeerFailure(f"node {node_id}: no neighbour for {peer_timeout:.0f} s in round {rnd} "
                                      f"(neighbour(s) {sorted(neighbours)} left or went silent)")
            else:
                alone_since = None
            if now - last_resend > resend_after:
                send_state()
                if updated:
                    send_complete()
                stats.resends += 1
                last_resend = now
            continue  # the neighbours left out may let the round advance
        t0 = time.perf_counter()
        timeout = CHECK_EVERY_S
        if round_wait > 0:  # wake when this round's wait for States or RoundCompletes is over
            due = round_started + round_wait
            timeout = min(timeout, max(0.005, due - time.monotonic()))
        msg = transport.receive(timeout=timeout)
        stats.wait_s += time.perf_counter() - t0
        now = time.monotonic()
        if msg is not None:
            j = msg.sender
            if j not in neighbours:
                continue
            behind = msg.kind == "state" and msg.round >= newest.get(j, -1)  # not a replay of its own old States
            if msg.kind == "state":
                newest[j] = max(newest.get(j, -1), msg.round)
            if round_wait > 0 and (msg.round < rnd or msg.round > rnd + ROUNDS_AHEAD) and not joining:
                # Poor links: the team's rounds drift apart. A State of another round is the neighbour's
                # newest word all the same: kept (the newest) for a round that gets none from it. Nothing
                # is replayed: a neighbour behind catches up by itself, its rounds timing out.
                heard[j] = now
                if msg.kind == "state" and msg.round >= late.get(j, (-1, None))[0] and acceptable(msg, state):
                    late[j] = (msg.round, msg.params)
                continue
            if msg.round < rnd:  # a neighbour behind (restarted): send it the States it needs again
                if behind and msg.round in history and now - replayed.get((j, msg.round), -1e9) > resend_after:
                    replayed[(j, msg.round)] = now
                    log.info("node %d: neighbour %d is back at round %d; sending it rounds %d-%d again", node_id, j,
                             msg.round, msg.round, rnd)
                    for r in range(msg.round, rnd + 1):
                        transport.send_state(r, history[r])
                    stats.replayed += rnd + 1 - msg.round
                continue
            heard[j] = now
            if msg.kind == "complete":
                if msg.round <= rnd + ROUNDS_AHEAD:
                    buf.complete[msg.round].add(j)
                continue
            if j in buf.states[msg.round]:
                continue  # the first State of a round counts
            # Left behind: stuck in this round for longer than the neighbours wait for anyone, while
            # they are further ahead than they can replay. They left this node out (it was slow to
            # start, or starved of CPU): catch up with them rather than wait for rounds nobody will send.
            left_behind = (now - round_started > silent_after
                           and rnd + max(keep_rounds, ROUNDS_AHEAD) < msg.round <= max_rounds)
            jump = (joining and not updated and rnd + keep_rounds < msg.round <= max_rounds) or left_behind
            if msg.round > rnd + ROUNDS_AHEAD and not jump:
                if not (joining and msg.round <= rnd + keep_rounds):  # (those are the replay's, coming)
                    refuse(stats, node_id, msg, f"round {msg.round} while this node is at round {rnd}", "far-future")
                continue
            # A node catching up holds stale parameters: it cannot judge distances to them.
            stale = (joining and not updated) or left_behind
            if not acceptable(msg, None if stale else state):
                continue
            if jump:  # the team is too far ahead to replay: catch up with it
                log.info("node %d: neighbour %d is at round %d; catching up from round %d%s", node_id, j, msg.round, rnd,
                         f" (left behind for {now - round_started:.0f} s)" if left_behind else "")
                buf.states = defaultdict(dict, {r: v for r, v in buf.states.items() if r >= msg.round})
                buf.complete = defaultdict(set, {r: v for r, v in buf.complete.items() if r >= msg.round})
                rnd, updated, round_started = msg.round, False, now
                buf.states[rnd][j] = msg.params
                state = round_state = rejoin(state, dict(buf.states[rnd])) if rejoin is not None else state
                active = {j} | (active & buf.states[rnd].keys())
                returning = set(neighbours) - active
                stats.caught_up += 1
                send_state()
                continue
            buf.states[msg.round][j] = msg.params
            if j not in active:
                if msg.round == rnd and not updated:
                    active.add(j)
                    stats.rejoined += 1
                    log.info("node %d: neighbour %d back in round %d", node_id, j, rnd)
                else:
                    returning.add(j)
    deadline = time.monotonic() + linger
    final = buf.states[max_rounds]
    while not active <= final.keys() and time.monotonic() < deadline:
        msg = transport.receive(timeout=max(0.0, min(0.2, deadline - time.monotonic())))
        if msg is not None and msg.kind == "state" and msg.sender in neighbours and msg.round == max_rounds:
            final[msg.sender] = msg.params
    stats.final_peers = dict(final)
    return state


TimedUpdate = Callable[[int, np.ndarray, dict[int, np.ndarray]], np.ndarray]
DRAIN_PER_ROUND = 10_000  # on a clock, messages taken from the inbox before a round at most (a flood cannot stall it)


def run_timed(node_id: int, neighbours: set[int], rounds: int, state: np.ndarray, node_update: TimedUpdate,
              transport: Transport, every_s: float, *, start_round: int = 0, stats: ExchangeStats | None = None,
              stop: threading.Event | None = None, check_state: StateCheck | None = None,
              silent_after: float = 30.0, forget: Callable[[int], None] | None = None,
              linger: float = 5.0) -> np.ndarray:
    """Exchange on a clock (``learner.exchange_every_s``), as robots whose radios talk every
    ``every_s`` seconds: run training rounds ``start_round .. rounds - 1`` back to back, never
    waiting for anyone. Before a round, the node sends its State when ``every_s`` seconds have
    passed since it last did (and before its first round), and takes every State that has
    arrived meanwhile; ``node_update(round, state, fresh)`` gets the newest of each neighbour
    that came since the last round (none in most rounds: the update then trains against the
    States it already holds). No RoundComplete, no resends: a State lost is lost, the next one
    comes ``every_s`` seconds later. The team's round numbers drift apart; a State older than
    one already taken from the same neighbour (reordered) is ignored. ``check_state`` refuses
    implausible States as in :func:`run_algorithm1`, except that the robots train apart between
    exchanges: a State passes when it is plausible against this node's parameters or against any
    neighbour's newest State taken, and before the node has taken any (it starts, or resumed
    behind its team) only the tests that need no reference apply. A neighbour silent for
    ``silent_after`` seconds is forgotten (``forget(j)``: the update stops pulling towards its
    last State) until it sends again; a node never fails for want of neighbours. After the last round the node
    sends its final State (round ``rounds``) and waits up to ``linger`` seconds for its
    neighbours' final States (``stats.final_peers``, with the newest State of any that has not
    finished by then)."""
    stats = stats if stats is not None else ExchangeStats()
    newest: dict[int, tuple[int, np.ndarray]] = {}  # each neighbour's newest State taken: (round, vector)
    heard: dict[int, float] = {}
    forgotten: set[int] = set()
    last_sent = -math.inf

    def take(msg: Envelope, into: dict[int, np.ndarray], now: float) -> None:
        j = msg.sender
        if msg.kind != "state" or j not in neighbours or msg.round < newest.get(j, (-1, None))[0]:
            return  # RoundCompletes (a node on round-based exchange), strangers, reordered older States
        if check_state is not None:
            # The team drifts apart between exchanges: near this node's parameters or any
            # neighbour's newest is near enough. Before it has taken any State (starting, or
            # resumed behind its team) a node cannot judge distances: finiteness only.
            refs = [state, *(v for _, v in newest.values())] if newest else [None]
            reasons = []
            for ref in refs:
                reasons.append(check_state(msg.params, ref))
                if reasons[-1] is None:
                    break
            else:
                refuse(stats, node_id, msg, reasons[0], "implausible")  # (why, against its own parameters)
                return
        if j in forgotten:
            forgotten.discard(j)
            stats.rejoined += 1
            log.info("node %d: neighbour %d heard again at its round %d", node_id, j, msg.round)
        newest[j] = (msg.round, msg.params)
        heard[j] = now
        into[j] = msg.params

    for k in range(start_round, rounds):
        if stop is not None and stop.is_set():
            raise InterruptedError(f"node {node_id} stopped at round {k}")
        now = time.monotonic()
        if now - last_sent >= every_s:
            t0 = time.perf_counter()
            transport.send_state(k, state)
            stats.send_s += time.perf_counter() - t0
            last_sent = now
        t0 = time.perf_counter()
        arrived: dict[int, Envelope] = {}  # the newest of each neighbour: only those are judged (a flood costs no checks)
        for _ in range(DRAIN_PER_ROUND):
            msg = transport.receive(timeout=0.0)
            if msg is None:
                break
            if msg.sender not in arrived or msg.round >= arrived[msg.sender].round:
                arrived[msg.sender] = msg
        fresh: dict[int, np.ndarray] = {}
        for msg in arrived.values():
            take(msg, fresh, time.monotonic())
        stats.wait_s += time.perf_counter() - t0
        for j in [j for j, t in heard.items() if j not in forgotten and now - t > silent_after]:
            forgotten.add(j)
            stats.left_out += 1
            log.warning("node %d: neighbour %d has been silent for %.0f s; round %d goes on without its last State",
                        node_id, j, now - heard[j], k)
            if forget is not None:
                forget(j)
        state = node_update(k, state, dict(sorted(fresh.items())))
        stats.rounds_done += 1
    transport.send_state(rounds, state)
    deadline = time.monotonic() + linger
    while any(newest.get(j, (-1, None))[0] < rounds for j in neighbours - forgotten) and time.monotonic() < deadline:
        msg = transport.receive(timeout=max(0.0, min(0.2, deadline - time.monotonic())))
        if msg is not None:
            take(msg, {}, time.monotonic())
    stats.final_peers = {j: v for j, (_, v) in sorted(newest.items()) if j not in forgotten}
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

    With ``run`` (a run id), every message goes through the wire codec, as over Zenoh: encoded
    to its bytes, decoded and validated by each receiver, and its bytes counted
    (``bytes_sent`` per sender, ``bytes_received`` per receiver). Without it, messages pass as
    objects (Algorithm 1's tests, with vectors of any dtype).

    ``delay(sender, receiver, envelope) -> seconds`` may hold a message back, which reorders
    deliveries the way a network can.
    """

    def __init__(self, graph: dict[int, set[int]],
                 delay: Callable[[int, int, Envelope], float] | None = None, run: str | None = None):
        self.graph = graph
        self.delay = delay
        self.run = run
        self.queues = {i: queue.Queue() for i in graph}
        self.timers: list[threading.Timer] = []
        self.lost: set[int] = set()  # nodes that have left (as their liveliness tokens would say)
        self.bytes_sent: Counter[int] = Counter()
        self.bytes_received: Counter[int] = Counter()

    def transport(self, node: int) -> MemoryTransport:
        return MemoryTransport(self, node)

    def deliver(self, sender: int, env: Envelope, payload: bytes | None = None) -> None:
        """Queue ``env`` (or its ``payload``, when the hub speaks the wire codec) for every neighbour."""
        item = env if payload is None else (env.kind, payload)
        if payload is not None:
            self.bytes_sent[sender] += len(payload)
        for j in self.graph[sender]:
            wait = self.delay(sender, j, env) if self.delay else 0.0
            if wait > 0:
                timer = threading.Timer(wait, self.queues[j].put, args=(item,))
                timer.daemon = True
                self.timers.append(timer)
                timer.start()
            else:
                self.queues[j].put(item)


class MemoryTransport:
    """One node's end of a :class:`MemoryHub`."""

    def __init__(self, hub: MemoryHub, node: int):
        self.hub = hub
        self.node = node
        self.refused: Counter[str] = Counter()  # payloads the codec refused (wire mode)

    def send_state(self, round: int, params: np.ndarray) -> None:
        if self.hub.run is None:
            self.hub.deliver(self.node, Envelope("state", self.node, round, np.array(params, copy=True)))
        else:
            self.hub.deliver(self.node, Envelope("state", self.node, round),
                             encode_state(self.hub.run, self.node, round, params))

    def send_fields(self, round: int, fields: dict) -> None:
        """A State of another encoding (:mod:`~swarmmap.shared.compression`); needs the wire codec."""
        if self.hub.run is None:
            raise ValueError("compressed States need a MemoryHub that speaks the wire codec (run=...)")
        msg = State(run=self.hub.run, sender=self.node, round=round, **fields)
        self.hub.deliver(self.node, Envelope("state", self.node, round), encode(msg))

    def send_round_complete(self, round: int) -> None:
        if self.hub.run is None:
            self.hub.deliver(self.node, Envelope("complete", self.node, round))
        else:
            self.hub.deliver(self.node, Envelope("complete", self.node, round),
                             encode(RoundComplete(run=self.hub.run, sender=self.node, round=round)))

    def receive(self, timeout: float) -> Envelope | None:
        try:
            item = self.hub.queues[self.node].get(timeout=timeout)
        except queue.Empty:
            return None
        if isinstance(item, Envelope):
            return item
        kind, payload = item
        self.hub.bytes_received[self.node] += len(payload)
        try:
            if kind == "complete":
                msg = decode(payload, RoundComplete, run=self.hub.run)
                return Envelope("complete", msg.sender, msg.round)
            return state_envelope(decode(payload, State, run=self.hub.run))
        except ProtocolError as exc:
            self.refused[exc.reason] += 1
            return None

    def lost_peers(self) -> set[int]:
        return self.hub.lost - {self.node}

    def wire_bytes(self) -> tuple[int, int]:
        """Bytes this node sent and received on Algorithm 1's links (wire mode)."""
        return self.hub.bytes_sent[self.node], self.hub.bytes_received[self.node]


def state_envelope(msg: State) -> Envelope:
    """A received State as Algorithm 1 takes it: an uncompressed one's vector as a read-only view
    of the payload; any other, the message itself (a :class:`StateCodec` rebuilds its vector)."""
    return Envelope("state", msg.sender, msg.round, msg.params.numpy() if msg.plain else msg)
