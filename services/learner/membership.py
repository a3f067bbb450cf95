"""Who an Algorithm 1 round waits for, and what a node keeps for the neighbours that lag.

Robots come and go (the paper assumes they do not). :class:`Membership` holds the neighbours a
round waits for (``active``): one whose liveliness token vanished (and did not come back within
``rejoin_wait`` seconds, the time a launcher needs to restart it), that stayed silent for
``silent_after`` seconds while this node waited on it (silent: no step forward, whatever it
repeats; COMPLETE_WAIT times as long while it owes the RoundComplete of a round whose State this
node took, NEXT_STATE_WAIT times once it completed a round and owes its next State: it may itself
be waiting on a silent neighbour, or on one that owes its RoundComplete, and this node may have
moved on meanwhile: the wait must not spread to it), or
that sent only States this node refuses for that long, is left out, and the round finishes
with the neighbours the node has. It is taken back once its State of the round at hand is here
(one of a later round alone brings it back at that round, not before), except the
REFUSED_OUT_FOR_GOOD-th time it is left out for refused States, or for a State whose
RoundComplete never came (counting its silences before: an honest node always completes the
round it sent a State for, unless it is gone): then for good (each return cost the team ``silent_after`` again, and on a sparse
graph the wait spreads to the neighbours' own neighbours).
Silence is counted while the node waits, not while it computes (:meth:`Progress.paused`).

A neighbour left out because it was gone (its liveliness token vanished: its host lost, a link
cut, a partition) learnt apart meanwhile, and so did this node: their parameters may then lie
farther apart than the screen's distance limit, and each would refuse the other for good. For
REUNION_ROUNDS rounds after its return, its States pass the screen's other checks only and are
pulled within the limit (``clip``) before the update, so each moves the other by at most what the
limit allows, and the two parts of the team meet again. A neighbour left out while its token
stayed (silent, or sending refused States) gets no reunion: a member that goes quiet for a while
must not win a looser check by it (a liar silent once then had its lies pulled in for 50 rounds).

:class:`Replay` keeps the States a node sent in its last ``keep_rounds`` rounds and sends them
again to a neighbour that restarted behind, so that it replays the rounds it lost with exactly
the States its neighbours had. :class:`LateStates` (poor links, ``round_wait``) keeps each
neighbour's newest State of another round for a round that gets none of its own from it.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from swarmmap.services.learner.exchange import ExchangeRules, ExchangeStats, PeerFailure, RoundCheck, StateCheck, refuse
from swarmmap.services.learner.transport import Envelope, Transport

log = logging.getLogger("learner")
Clip = Callable[[np.ndarray, np.ndarray], np.ndarray]  # clip(theirs, own): theirs pulled within the screen's limit
REUNION_ROUNDS = 50  # rounds after a neighbour's return in which its far States are pulled in, not refused
REFUSED_OUT_FOR_GOOD = 2  # left out this often for sending only refused States: left out for the rest of the run
COMPLETE_WAIT = 2  # a neighbour that owes the RoundComplete of a State taken has this many times silent_after for it
NEXT_STATE_WAIT = 3  # one that completed a round and owes its next State (it may wait COMPLETE_WAIT for another)
RESEND_BACKOFF = 8  # a round's messages go again after resend_after seconds, then twice as long, up to 8 times it


@dataclass
class RoundBuffer:
    """Messages buffered per round: an early State waits for its round, rounds never mix."""

    states: dict[int, dict[int, np.ndarray]] = field(default_factory=lambda: defaultdict(dict))
    complete: dict[int, set[int]] = field(default_factory=lambda: defaultdict(set))

    def drop(self, rnd: int) -> None:
        """Forget round ``rnd`` (finished)."""
        self.states.pop(rnd, None)
        self.complete.pop(rnd, None)

    def held(self, j: int, r: int) -> np.ndarray | None:
        """``j``'s State of round ``r``, if this node holds one."""
        return self.states[r].get(j) if r in self.states else None

    def forget_sender(self, j: int) -> None:
        """Drop every State of ``j`` this node holds."""
        for states in self.states.values():
            states.pop(j, None)

    def keep_from(self, rnd: int) -> None:
        """Forget every round before ``rnd`` (a node that jumped ahead)."""
        self.states = defaultdict(dict, {r: v for r, v in self.states.items() if r >= rnd})
        self.complete = defaultdict(set, {r: v for r, v in self.complete.items() if r >= rnd})

    def still_needed(self, among: set[int], rnd: int, updated: bool) -> set[int]:
        """The neighbours of ``among`` that round ``rnd`` still waits on: their State before the
        update, after it their RoundComplete (none once one has moved on to the next round)."""
        if not updated:
            return among - self.states[rnd].keys()
        if any(j in self.states[rnd + 1] for j in among):
            return set()
        return among - self.complete[rnd]


class Reunion:
    """A neighbour left out because it was gone (a lost host, a cut link) learnt apart meanwhile;
    once back, its States farther than the screen's limit are taken pulled within it (``clip``),
    not refused, for REUNION_ROUNDS rounds, so two parts of a team meet again."""

    def __init__(self, clip: Clip | None):
        self.clip = clip
        self.away: set[int] = set()  # left out as gone
        self.until: dict[int, int] = {}  # neighbour -> the last round its far States are pulled in

    def __call__(self, j: int, rnd: int) -> bool:
        """Whether neighbour ``j``'s States of round ``rnd`` are taken pulled in when far: it was left
        out as gone, and is not back yet or came back at most REUNION_ROUNDS ago."""
        return self.clip is not None and (j in self.away or rnd <= self.until.get(j, -1))

    def back(self, j: int, rnd: int) -> None:
        """Neighbour ``j`` is waited for again from round ``rnd``: a reunion when it had been away."""
        if j in self.away:
            self.away.discard(j)
            self.until[j] = rnd + REUNION_ROUNDS


class Progress:
    """When each neighbour last moved forward (a State taken, or the RoundComplete of one), what it
    owes (the RoundComplete of a State taken, or the State after a RoundComplete), and since when it
    has sent only States this node refuses."""

    def __init__(self, neighbours: set[int]):
        self.heard = dict.fromkeys(neighbours, time.monotonic())  # the last step forward of each neighbour
        self.owes: dict[int, int] = {}  # per neighbour: the round of its State taken whose RoundComplete has not come
        self.between: set[int] = set()  # neighbours that completed a round whose next State has not come
        self.refused_since: dict[int, float] = {}  # per neighbour: its first refused State since one this node took

    def heard_from(self, j: int, now: float) -> None:
        self.heard[j] = now

    def took_state(self, j: int, r: int, now: float) -> None:
        """``j``'s State of round ``r`` was taken: a step forward; its RoundComplete of ``r`` is owed."""
        self.heard[j] = now
        self.owes[j] = max(self.owes.get(j, r), r)
        self.between.discard(j)

    def completed(self, j: int, r: int, now: float) -> None:
        """``j``'s RoundComplete of round ``r``: a step forward where it completes a State taken
        (whatever round this node is at: one that moved on still hears it finish)."""
        if self.owes.get(j, r + 1) <= r:
            del self.owes[j]
            self.between.add(j)
            self.heard[j] = now

    def patience(self, j: int) -> int:
        """How many times ``silent_after`` neighbour ``j`` gets for its next step forward."""
        return COMPLETE_WAIT if j in self.owes else NEXT_STATE_WAIT if j in self.between else 1

    def forget(self, j: int) -> None:
        """``j`` is left out: what it owed no longer counts (back, it starts afresh)."""
        self.owes.pop(j, None)
        self.between.discard(j)
        self.refused_since.pop(j, None)

    def paused(self, busy: float) -> float:
        """Silence counts while the node listens, not while it computed (``busy`` s, returned: it waits in its inbox)."""
        for j in self.heard:
            self.heard[j] += busy
            if j in self.refused_since:
                self.refused_since[j] += busy
        return busy


class Membership:
    """The neighbours a node's rounds wait for, and when each was last heard."""

    def __init__(self, node_id: int, neighbours: set[int], rules: ExchangeRules, stats: ExchangeStats, clip: Clip | None = None):
        self.node_id, self.neighbours, self.rules, self.stats = node_id, frozenset(neighbours), rules, stats
        self.active = set(neighbours)  # the neighbours this round waits for
        self.returning: set[int] = set()  # left out, but sent a State of a later round: back once one of the round at hand is here
        self.progress = Progress(neighbours)
        self.banned: set[int] = set()  # said two different things for one round: never heard again
        self.refusals_out: dict[tuple[int, str], int] = {}  # (neighbour, why): how often it was left out for a fault of its own
        self.lost_since: dict[int, float] = {}  # when each neighbour's token vanished; when none was left
        self.alone_since: float | None = None
        self.reunion = Reunion(clip)

    def judge(self, msg: Envelope, check: StateCheck | None, own: np.ndarray | None) -> bool:
        """Whether a neighbour's State passes ``check`` (against ``own``); a refused one is counted,
        and when the neighbour's refused States began is kept (it is left out if they go on)."""
        why = check(msg.params, own) if check is not None else None
        if why is not None and own is not None and self.reunion(msg.sender, msg.round) and hasattr(check, "loose"):
            why = check.loose(msg.params, own)  # far is expected after learning apart: pulled in at the update
        if why is None:
            self.progress.refused_since.pop(msg.sender, None)
            return True
        self.progress.refused_since.setdefault(msg.sender, time.monotonic())
        refuse(self.stats, self.node_id, msg, why, "implausible")
        return False

    def equivocates(self, msg: Envelope, buf: RoundBuffer, late: LateStates, rnd: int) -> bool:
        """Whether ``msg`` (a plausible State of a round this node holds one of from the same
        sender) says something else, in an encoding that repeats itself exactly (float32, half
        precision): the sender is then banned and everything it said dropped. A compressed chain's
        States are not compared (a resend after a replay re-encodes them)."""
        held = buf.held(msg.sender, msg.round)
        if msg.kind != "state" or not msg.exact or held is None or np.array_equal(held, msg.params):
            return False
        self.ban(msg.sender, f"sent two different States for round {msg.round}", rnd)
        buf.forget_sender(msg.sender)
        late.late.pop(msg.sender, None)
        return True

    def ban(self, j: int, why: str, rnd: int, reason: str = "equivocation") -> None:
        """``j`` is hostile (it said two different things for one round, or was left out again for
        sending only refused States): left out for good."""
        if j in self.banned:
            return
        self.banned.add(j)
        self.active.discard(j)
        self.returning.discard(j)
        self.progress.forget(j)
        self.stats.refused[reason] += 1
        self.stats.refused_from[j] += 1
        self.stats.left_out += 1
        log.warning("node %d: neighbour %d %s; it is left out for the rest of the run (round %d)", self.node_id, j, why, rnd)

    def leave_out(self, j: int, why: str, rnd: int) -> None:
        self.active.discard(j)
        self.progress.forget(j)
        self.stats.left_out += 1
        log.warning("node %d: neighbour %d %s; round %d goes on without it", self.node_id, j, why, rnd)

    def out_again(self, j: int, why: str, rnd: int, reason: str, before: int = 0) -> None:
        """Leave ``j`` out for a fault of its own (``reason``); the REFUSED_OUT_FOR_GOOD-th time for
        good, counting ``before`` earlier faults (an incomplete State after a silence: an honest
        node taken back after a silence completes the round it sent a State for)."""
        self.refusals_out[(j, reason)] = times = self.refusals_out.get((j, reason), 0) + 1 + before
        if times < REFUSED_OUT_FOR_GOOD:
            return self.leave_out(j, why, rnd)
        self.ban(j, f"{why}, after {before} silence(s) of its own" if before else f"{why}, for the {times}nd time", rnd, reason)

    def came_back(self, j: int, rnd: int, now_round: bool) -> None:
        """Neighbour ``j``, left out, sent a State: of the round at hand before the update
        (``now_round``: taken back at once) or of a later one (back from the next round)."""
        if j in self.banned:
            return
        if now_round:
            self.returning.discard(j)
            self.active.add(j)
            self.reunion.back(j, rnd)
            self.stats.rejoined += 1
            log.info("node %d: neighbour %d back in round %d", self.node_id, j, rnd)
        else:
            self.returning.add(j)

    def vouched(self, newest: dict[int, int], r: int) -> bool:
        """Whether enough of the neighbours still here (not banned, not gone) have sent States of
        round ``r`` or later (``newest``) for this node to jump there (:func:`corroborated`)."""
        return corroborated(newest, set(self.neighbours) - self.banned - self.lost_since.keys(), r)

    def next_round(self, rnd: int, holds: Callable[[int], bool] = lambda j: True) -> None:
        """Round ``rnd`` begins: the neighbours returning whose State of it is here (``holds``) are
        waited for again; the others once it comes (a State of a later round alone does not bring
        a neighbour back: an honest one sends every round's, one that skips rounds would cost
        each round ``silent_after`` of waiting)."""
        back = {j for j in self.returning if holds(j)}
        if back:
            log.info("node %d: neighbour(s) %s back from round %d", self.node_id, sorted(back), rnd)
            self.active.update(back)
            for j in back:
                self.reunion.back(j, rnd)
            self.stats.rejoined += len(back)
            self.returning -= back

    def jumped(self, j: int, present: set[int], rnd: int) -> None:
        """The node caught up with neighbour ``j``'s round, where ``present`` sent their States
        too: they are waited for; the others come back once they reach it."""
        self.active = {j} | (self.active & present)
        self.returning = set(self.neighbours) - self.active - self.banned
        for k in self.active:
            self.reunion.back(k, rnd)

    def check(self, needed: set[int], lost: set[int], rnd: int, now: float) -> None:
        """Leave out the neighbours of ``needed`` that are gone (``lost``), silent, or sending only
        refused States; fail with :class:`PeerFailure` when none has been left for ``peer_timeout``.
        A neighbour is silent when it has not moved forward for ``silent_after`` seconds, or for
        :meth:`Progress.patience` times that once it takes part (it may itself wait on a neighbour
        of its own, and this node may have gone on to the next round meanwhile: the wait must not
        spread to it)."""
        self.lost_since = {j: self.lost_since.get(j, now) for j in lost}
        r, p = self.rules, self.progress
        for j in sorted(needed & self.active):
            owed, silent_after = j in p.owes, r.silent_after * p.patience(j)
            if j in lost and now - self.lost_since[j] >= r.rejoin_wait:
                self.leave_out(j, "left (its liveliness token vanished)" + (
                    f" and is not back after {r.rejoin_wait:.0f} s" if r.rejoin_wait else ""), rnd)
                self.reunion.away.add(j)
            elif now - p.refused_since.get(j, now) > r.silent_after:  # it talks, but only in refused States
                why = f"has sent only States this node refuses for {now - p.refused_since[j]:.0f} s"
                self.out_again(j, why, rnd, "refused")
            elif now - p.heard[j] > silent_after and owed:  # its State was taken, its RoundComplete never came
                self.out_again(j, f"sent its State of round {p.owes[j]} but no RoundComplete for "
                                  f"{now - p.heard[j]:.0f} s", rnd, "incomplete", self.refusals_out.get((j, "silent"), 0))
            elif now - p.heard[j] > silent_after:
                self.refusals_out[(j, "silent")] = self.refusals_out.get((j, "silent"), 0) + 1
                self.leave_out(j, f"has been silent for {now - p.heard[j]:.0f} s", rnd)
        if self.neighbours and not self.active:
            self.alone_since = self.alone_since or now
            if now - self.alone_since > r.peer_timeout:
                raise PeerFailure(f"node {self.node_id}: no neighbour for {r.peer_timeout:.0f} s in round {rnd} "
                                  f"(neighbour(s) {sorted(self.neighbours)} left or went silent)")
        else:
            self.alone_since = None


def round_states(members: Membership, screen: RoundCheck | None, own: np.ndarray, peers: dict[int, np.ndarray],
                 late: LateStates, rnd: int) -> dict[int, np.ndarray]:
    """The States round ``rnd``'s update takes: ``members``' active neighbours' of the round, judged
    together (``screen``: the outliers are refused for this round, counted; an honest node far
    from the rest is refused only while it is), then, for the others, their late States
    (poor links). Neighbours with neither are counted as missed."""
    reunion = members.reunion
    fresh = {j: reunion.clip(peers[j], own) if reunion(j, rnd) else peers[j] for j in members.active & peers.keys()}
    refused = screen(own, fresh) if screen is not None and fresh else {}
    for j, why in refused.items():
        refuse(members.stats, members.node_id, Envelope("state", j, rnd), why, "outlier")
    used = late.fill({j: v for j, v in fresh.items() if j not in refused}, members.active - refused.keys(), rnd)
    members.stats.missed += len(members.active) - len(fresh.keys() | used.keys())
    return used


def corroborated(newest: dict[int, int], trusted: set[int], r: int) -> bool:
    """Whether enough trusted neighbours (two, or every one of a node with one) have sent States of
    round ``r`` or later (``newest``: each one's newest round) for a node to jump there: a lone
    State cannot take it to the end."""
    return sum(1 for j, k in newest.items() if j in trusted and k >= r) >= min(2, len(trusted))


class Replay:
    """A node's own States of its last ``keep_rounds`` rounds, sent again to a neighbour behind."""

    def __init__(self, node_id: int, keep_rounds: int, resend_after: float, stats: ExchangeStats):
        self.node_id, self.keep_rounds, self.resend_after, self.stats = node_id, keep_rounds, resend_after, stats
        self.history: dict[int, np.ndarray] = {}
        self.replayed: dict[tuple[int, int], tuple[float, float]] = {}  # (neighbour, round) -> when seen or replayed, wait before the next
        self.newest: dict[int, int] = {}  # newest round of a State from each neighbour (forgotten when it leaves)

    def remember(self, rnd: int, state: np.ndarray) -> None:
        self.history[rnd] = state
        for old in [r for r in self.history if r < rnd - self.keep_rounds]:
            del self.history[old]
        for old in [key for key in self.replayed if key[1] < rnd - self.keep_rounds]:
            del self.replayed[old]

    def seen(self, j: int, r: int) -> bool:
        """Note neighbour ``j``'s State of round ``r``; whether it is its newest word (not a
        replay of its own old States, which a restarted neighbour's neighbours send it)."""
        newest = r >= self.newest.get(j, -1)
        self.newest[j] = max(self.newest.get(j, -1), r)
        return newest

    def forget(self, lost: set[int]) -> None:
        for j in lost:
            self.newest.pop(j, None)

    def answer(self, j: int, r: int, rnd: int, transport: Transport, now: float) -> None:
        """Neighbour ``j`` is back at round ``r`` < ``rnd``: send it rounds ``r .. rnd`` again
        when it is still there ``resend_after`` seconds after it was first seen there (a
        neighbour a round behind on a slow link mostly has what it needs and is on its way),
        then after twice as long each time, up to RESEND_BACKOFF times ``resend_after``."""
        if r not in self.history:
            return
        last, wait = self.replayed.get((j, r), (None, self.resend_after))
        if last is None:
            self.replayed[(j, r)] = (now, wait)
            return
        if now - last <= wait:
            return
        self.replayed[(j, r)] = (now, min(2 * wait, RESEND_BACKOFF * self.resend_after))
        log.info("node %d: neighbour %d is back at round %d; sending it rounds %d-%d again", self.node_id, j, r, r, rnd)
        for k in range(r, rnd + 1):
            transport.send_state(k, self.history[k])
        self.stats.replayed += rnd + 1 - r


class LateStates:
    """Poor links: each neighbour's newest State of another round than the one at hand."""

    def __init__(self) -> None:
        self.late: dict[int, tuple[int, np.ndarray]] = {}

    def newest_round(self, j: int) -> int:
        return self.late.get(j, (-1, None))[0]

    def keep(self, j: int, r: int, params: np.ndarray) -> None:
        self.late[j] = (r, params)

    def offer(self, msg: Envelope, judge) -> bool:
        """A State of another round is the neighbour's newest word: kept for a round that gets none
        from it when it is newer than the one kept and passes ``judge`` (nothing is replayed: a
        node behind catches up by its rounds' timeouts). Whether it was kept."""
        if msg.kind == "state" and msg.round > self.newest_round(msg.sender) and judge(msg):
            self.keep(msg.sender, msg.round, msg.params)
            return True
        return False

    def fill(self, used: dict[int, np.ndarray], active: set[int], rnd: int) -> dict[int, np.ndarray]:
        """``used`` (the States of round ``rnd``), with the newest late State of every active
        neighbour that sent none of this round; late States older than this round's are dropped."""
        for j in list(self.late):
            if j in used and self.late[j][0] <= rnd:
                del self.late[j]  # older than the State of this round
            elif j in active and j not in used:
                used[j] = self.late.pop(j)[1]  # this round's did not come: the newest of another round
        return used
