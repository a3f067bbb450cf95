"""Algorithm 1 (and the clock mode) over the in-memory transport: rounds never mix, delays and reordering change
nothing, dead or silent peers are named."""

from __future__ import annotations

import logging
import random
import threading
import time
from collections import Counter

import numpy as np
import pytest

from swarmmap.services.learner.algorithm1 import Algorithm1, RoundLoop
from swarmmap.services.learner.clock import ClockExchange
from swarmmap.services.learner.exchange import ExchangeRules, ExchangeStats, PeerFailure
from swarmmap.services.learner.membership import Replay
from swarmmap.services.learner.screening import implausible
from swarmmap.services.learner.transport import Envelope, Inbox, MemoryHub

COMPLETE3 = {0: {1, 2}, 1: {0, 2}, 2: {0, 1}}


def run_algorithm1(node, neighbours, rounds, state, update, transport, *, start_round=0, resumed=False, stats=None,
                   stop=None, check_state=None, check_stale=None, rejoin=None, pace=None, **rules):
    """Algorithm 1 at one node as the learner composes it: the round machine driven by a RoundLoop."""
    machine = Algorithm1(node, neighbours, update, transport, ExchangeRules(**rules), check=check_state,
                         check_stale=check_stale, rejoin=rejoin, stats=stats, stop=stop)
    return RoundLoop(machine, pace).run(state, rounds, start_round, resumed)


def run_timed(node, neighbours, rounds, state, update, transport, every_s, *, start_round=0, stats=None, stop=None,
              check_state=None, forget=None, **rules):
    """The clock mode at one node."""
    return ClockExchange(node, neighbours, update, transport, every_s, ExchangeRules(**rules), check=check_state,
                         forget=forget, stats=stats, stop=stop).run(state, rounds, start_round)
RING4 = {0: {1, 3}, 1: {0, 2}, 2: {1, 3}, 3: {2, 0}}


def mixing_update(node: int):
    """A deterministic node update that depends on the round and on exactly which peer states it got."""

    def update(k: int, theta: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        return (theta + sum(peers.values())) / (1 + len(peers)) + 0.01 * (k + 1) * (node + 1)

    return update


def slowed_update(node: int, seconds):
    """mixing_update that first takes ``seconds(round)`` of compute (a slow or starved node)."""
    update = mixing_update(node)

    def step(k, theta, peers):
        threading.Event().wait(seconds(k))
        return update(k, theta, peers)

    return step


def reference(graph, rounds, init):
    """The synchronous in-process loop: every node updates from everyone's round-k state."""
    thetas = dict(init)
    for k in range(rounds):
        thetas = {i: mixing_update(i)(k, thetas[i], {j: thetas[j] for j in sorted(graph[i])}) for i in graph}
    return thetas


def in_threads(graph, body, timeout=60):
    """``body(i)`` for every node of ``graph``, each in a thread of its own: what each returned
    and what each raised (for the test to check)."""
    results, errors = {}, {}

    def node(i):
        try:
            results[i] = body(i)
        except Exception as exc:  # collected for the test
            errors[i] = exc

    threads = [threading.Thread(target=node, args=(i,)) for i in graph]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout)
    return results, errors


def run_threads(graph, rounds, init, delay=None, **kw):
    hub = MemoryHub(graph, delay)
    return in_threads(graph, lambda i: run_algorithm1(i, graph[i], rounds, init[i], mixing_update(i), hub.transport(i),
                                                      peer_timeout=kw.get("peer_timeout", 20), resend_after=0.2,
                                                      linger=0.5))


@pytest.mark.parametrize("graph", [COMPLETE3, RING4], ids=["complete", "ring"])
def test_matches_the_synchronous_reference(graph):
    init = {i: np.full(4, float(i)) for i in graph}
    results, errors = run_threads(graph, 12, init)
    assert not errors
    ref = reference(graph, 12, init)
    for i in graph:
        np.testing.assert_allclose(results[i], ref[i], rtol=0, atol=1e-12)


def test_random_delays_and_reordering_change_nothing():
    rng = random.Random(3)
    lock = threading.Lock()

    def delay(sender, receiver, env):
        with lock:
            return rng.choice([0.0, 0.0, 0.01, 0.03, 0.06])

    init = {i: np.full(3, float(i) ** 2) for i in RING4}
    results, errors = run_threads(RING4, 15, init, delay)
    assert not errors
    ref = reference(RING4, 15, init)
    for i in RING4:
        np.testing.assert_allclose(results[i], ref[i], rtol=0, atol=1e-12)


def test_future_state_is_buffered_and_stale_messages_ignored():
    """Feed one node a scripted stream: an early round-1 State, duplicates and stale messages."""

    class Scripted:
        def __init__(self, msgs):
            self.msgs = list(msgs)
            self.sent = []

        def send_state(self, r, p):
            self.sent.append(("state", r))

        def send_round_complete(self, r):
            self.sent.append(("complete", r))

        def receive(self, timeout):
            return self.msgs.pop(0) if self.msgs else None

        def lost_peers(self):
            return set()

    seen = []

    def update(k, theta, peers):
        seen.append((k, {j: float(v[0]) for j, v in peers.items()}))
        return theta + 1

    t = Scripted([
        Envelope("state", 1, 1, np.array([11.0])),  # from the future: kept for round 1
        Envelope("state", 1, 0, np.array([10.0])),
        Envelope("state", 1, 0, np.array([99.0])),  # duplicate of round 0 after the update: ignored
        Envelope("complete", 1, 0),
        Envelope("complete", 1, 0),  # stale duplicate
        Envelope("state", 1, 0, np.array([98.0])),  # stale
        Envelope("complete", 1, 1),
    ])
    out = run_algorithm1(0, {1}, 2, np.array([0.0]), update, t, linger=0)
    assert seen == [(0, {1: 10.0}), (1, {1: 11.0})]
    assert out[0] == 2.0
    assert t.sent == [("state", 0), ("complete", 0), ("state", 1), ("complete", 1), ("state", 2)]


def test_node_without_neighbours_trains_alone():
    hub = MemoryHub({0: set()})
    stats = ExchangeStats()
    out = run_algorithm1(0, set(), 5, np.zeros(2), lambda k, th, p: th + 1, hub.transport(0), stats=stats, linger=0)
    assert out.tolist() == [5.0, 5.0] and stats.rounds_done == 5


def test_a_node_left_without_neighbours_fails_after_the_timeout_naming_them(caplog):
    hub = MemoryHub({0: {1}, 1: {0}})
    with pytest.raises(PeerFailure, match=r"no neighbour for 1 s .*neighbour\(s\) \[1\]"):
        run_algorithm1(0, {1}, 3, np.zeros(1), lambda k, th, p: th, hub.transport(0), peer_timeout=1,
                       resend_after=0.1, silent_after=0.3)
    assert "neighbour 1 has been silent" in caplog.text


def test_a_lost_neighbour_is_left_out_and_named(caplog):
    hub = MemoryHub({0: {1}, 1: {0}})
    transport = hub.transport(0)
    transport.lost_peers = lambda: {1}
    with pytest.raises(PeerFailure, match="no neighbour"):
        run_algorithm1(0, {1}, 3, np.zeros(1), lambda k, th, p: th, transport, peer_timeout=0.5, resend_after=0.1)
    assert "neighbour 1 left (its liveliness token vanished); round 0 goes on without it" in caplog.text


def test_implausible_states_are_named():

    own = np.linspace(-1, 1, 100)
    assert implausible(own + 0.01, own, 0.5) is None
    assert "constant" in implausible(np.zeros(100), own, 0.5)
    assert "x the own parameters' norm away" in implausible(own * 3, own, 0.5)
    assert "parameters, expected" in implausible(np.ones(3), own, 0.5)
    assert "non-finite" in implausible(np.full(100, np.nan), own, 0.5)


def test_hostile_and_far_future_states_are_refused_and_the_rounds_go_on():
    """A hostile member sends zero States for rounds 0-2 before the honest ones and States far
    in the future: node 0 refuses them (counted), and ends exactly where the clean run ends."""

    graph = {0: {1}, 1: {0}}
    init = {0: np.linspace(1, 2, 8), 1: np.linspace(1, 2, 8)}
    ref = reference(graph, 8, init)
    hub = MemoryHub(graph)
    for k in (0, 1, 2):
        hub.queues[0].put(Envelope("state", 1, k, np.zeros(8)))
    hub.queues[0].put(Envelope("state", 1, 10_000, np.ones(8)))
    stats = ExchangeStats()
    results, _ = in_threads(graph, lambda i: run_algorithm1(
        i, graph[i], 8, init[i], mixing_update(i), hub.transport(i), resend_after=0.2, linger=0.5,
        stats=stats if i == 0 else None, check_state=lambda theirs, own: implausible(theirs, own, 0.5)))
    np.testing.assert_array_equal(results[0], ref[0])
    assert stats.refused["implausible"] == 3 and stats.refused["far-future"] == 1


def test_faulty_links_lose_duplicate_and_reorder_yet_the_result_is_the_reference():
    """30% of messages lost, 20% duplicated, delays that reorder: Algorithm 1 resends and still
    ends exactly where the synchronous reference ends."""
    from swarmmap.services.learner.faults import FaultyTransport
    from swarmmap.shared.run.config import FaultSettings

    faults = FaultSettings(link_success=0.7, duplicate=0.2, delay_s=0.02, seed=5)
    graph, init = COMPLETE3, {i: np.full(4, float(i)) for i in COMPLETE3}
    hub = MemoryHub(graph)
    transports = {i: FaultyTransport(hub.transport(i), i, faults) for i in graph}
    results, _ = in_threads(graph, lambda i: run_algorithm1(i, graph[i], 12, init[i], mixing_update(i), transports[i],
                                                          resend_after=0.05, linger=0.5), timeout=120)
    ref = reference(graph, 12, init)
    for i in graph:
        np.testing.assert_allclose(results[i], ref[i], rtol=0, atol=1e-12)
    assert sum(t.dropped for t in transports.values()) > 20 and sum(t.duplicated for t in transports.values()) > 5


def test_a_node_that_crashes_and_resumes_from_its_checkpoint_replays_and_ends_as_the_reference():
    """Node 2 crashes in round 7; its neighbours wait for it; it resumes from its round-5
    checkpoint, replays rounds 5-7 with the States its neighbours send again, and every node ends
    exactly where the uninterrupted reference ends."""
    graph, rounds = COMPLETE3, 12
    init = {i: np.full(4, float(i)) for i in graph}
    ref, at_5 = reference(graph, rounds, init), reference(graph, 5, init)
    hub = MemoryHub(graph)
    results, crashed = {}, threading.Event()

    class Crash(Exception):
        pass

    def crashing(k, theta, peers):
        if k == 7:
            hub.lost.add(2)
            crashed.set()
            raise Crash
        return mixing_update(2)(k, theta, peers)

    def node(i, update, **kw):
        try:
            results[i] = run_algorithm1(i, graph[i], rounds, kw.pop("state", init[i]), update, hub.transport(i),
                                        resend_after=0.2, linger=0.5, rejoin_wait=30, keep_rounds=4, **kw)
        except Crash:
            pass

    threads = [threading.Thread(target=node, args=(i, mixing_update(i))) for i in (0, 1)]
    threads.append(threading.Thread(target=node, args=(2, crashing)))
    for t in threads:
        t.start()
    assert crashed.wait(30)
    threads[2].join(10)
    while not hub.queues[2].empty():  # the crashed process's inbox is gone with it
        hub.queues[2].get()
    threading.Event().wait(1.0)  # a restart takes a while: the neighbours see the node gone (they poll every 0.5 s)
    hub.lost.discard(2)
    restarted = threading.Thread(target=node, args=(2, mixing_update(2)),
                                 kwargs={"state": at_5[2], "start_round": 5, "resumed": True})
    restarted.start()
    for t in (*threads[:2], restarted):
        t.join(60)
    for i in graph:
        np.testing.assert_allclose(results[i], ref[i], rtol=0, atol=1e-12)


def test_a_node_left_behind_catches_up_with_its_team_instead_of_waiting_forever(caplog):
    """Node 2 starts late (a slow start, a starved CPU): its neighbours leave it out as silent
    and go on. When it comes, they are further ahead than they can replay; once it has been
    stuck for silent_after it jumps to their round, they take it back, and every node finishes."""
    caplog.set_level(logging.INFO)
    graph, rounds = COMPLETE3, 80
    init = {i: np.full(4, float(i)) for i in graph}
    hub = MemoryHub(graph)
    results, stats = {}, {i: ExchangeStats() for i in graph}

    def slow(i):
        return slowed_update(i, lambda k: 0.05)  # 80 rounds take the others about 4 s

    def node(i):
        results[i] = run_algorithm1(i, graph[i], rounds, init[i], slow(i), hub.transport(i), stats=stats[i],
                                    resend_after=0.2, linger=0.5, silent_after=0.6, keep_rounds=2, peer_timeout=30)

    threads = {i: threading.Thread(target=node, args=(i,)) for i in graph}
    for i in (0, 1):
        threads[i].start()
    threading.Event().wait(1.2)  # node 2 starts late: 0 and 1 have left it out and are rounds ahead
    while not hub.queues[2].empty():  # what was sent before it started never reached it
        hub.queues[2].get()
    threads[2].start()
    for t in threads.values():
        t.join(30)
    assert sorted(results) == [0, 1, 2], "a node was still waiting"
    assert stats[2].caught_up == 1 and stats[2].rounds_done < rounds - 5, "node 2 should have jumped ahead"
    assert stats[0].rejoined >= 1 and stats[1].rejoined >= 1, "its neighbours should have taken it back"
    assert "left behind" in caplog.text


def test_a_node_busy_computing_longer_than_silent_after_does_not_leave_out_its_neighbours():
    """Round 0's update of every node takes longer than silent_after (a first optimizer step
    that loads libraries, an evaluation, 32 learners on 2 cores): the neighbours' States that
    arrived meanwhile wait in the inbox, so nobody is left out and every round has every
    neighbour."""
    graph, rounds = COMPLETE3, 6
    init = {i: np.full(4, float(i)) for i in graph}
    hub = MemoryHub(graph)
    stats = {i: ExchangeStats() for i in graph}

    def slow_first(i):
        return slowed_update(i, lambda k: 1.0 + 0.3 * i if k == 0 else 0.0)  # > silent_after, and not all alike

    results, _ = in_threads(graph, lambda i: run_algorithm1(
        i, graph[i], rounds, init[i], slow_first(i), hub.transport(i), stats=stats[i], resend_after=5.0, linger=0.5,
        silent_after=0.6, peer_timeout=30), timeout=30)
    assert sorted(results) == [0, 1, 2]
    assert [stats[i].left_out for i in graph] == [0, 0, 0], "a busy node took its neighbours for gone"
    ref = reference(graph, rounds, init)
    for i in graph:
        np.testing.assert_allclose(results[i], ref[i], rtol=0, atol=1e-12)


def test_a_neighbour_whose_every_state_is_refused_is_left_out_and_the_rounds_go_on(caplog):
    """A member that keeps talking (States and RoundCompletes, all the time) but whose every
    State is refused is not waited on forever: after silent_after without a State this node
    could take, it is left out, named, and the others finish."""

    graph = {0: {1, 2}, 1: {0, 2}, 2: {0, 1}}
    hub = MemoryHub(graph)
    done = threading.Event()

    def hostile():
        while not done.is_set():
            for r in range(8):
                for q in (0, 1):
                    hub.queues[q].put(Envelope("state", 2, r, np.zeros(8)))
                    hub.queues[q].put(Envelope("complete", 2, r))
            done.wait(0.05)

    init = {i: np.linspace(1, 2, 8) + 0.01 * i for i in (0, 1)}
    stats, results = {0: ExchangeStats(), 1: ExchangeStats()}, {}

    def node(i):
        results[i] = run_algorithm1(i, graph[i], 5, init[i], mixing_update(i), hub.transport(i), resend_after=0.2,
                                    linger=0.2, stats=stats[i], silent_after=1.0, peer_timeout=20,
                                    check_state=lambda theirs, own: implausible(theirs, own, 0.5))

    threads = [threading.Thread(target=hostile)] + [threading.Thread(target=node, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads[1:]:
        t.join(30)
    done.set()
    threads[0].join(5)
    assert set(results) == {0, 1}
    assert all(s.left_out >= 1 and s.refused["implausible"] >= 1 for s in stats.values())
    assert "has sent only States this node refuses" in caplog.text


def team_with_member(graph, member, says, silent_after, delay=None, rounds=4, init=None, **rules):
    """The honest nodes of ``graph`` run ``rounds`` rounds while ``member`` only puts what
    ``says(round)`` gives (Envelopes, every 50 ms, the round counting up) in its neighbours'
    inboxes; ``silent_after(node)`` per honest node, ``init(node)`` its start. Every honest node
    must finish its rounds; returns their stats."""
    hub = MemoryHub(graph, delay)
    done = threading.Event()
    honest = sorted(set(graph) - {member})
    stats, results = {i: ExchangeStats() for i in honest}, {}

    def speak():
        r = 0
        while not done.is_set():
            for q in graph[member]:
                for env in says(r):
                    hub.queues[q].put(env)
            r += 1
            done.wait(0.05)

    def node(i):
        start = init(i) if init is not None else np.full(4, float(i))
        results[i] = run_algorithm1(i, graph[i], rounds, start, mixing_update(i), hub.transport(i),
                                    **{"resend_after": 0.3, "linger": 0.2, "peer_timeout": 20, **rules},
                                    stats=stats[i], silent_after=silent_after(i))

    threads = [threading.Thread(target=speak)] + [threading.Thread(target=node, args=(i,)) for i in honest]
    for t in threads:
        t.start()
    for t in threads[1:]:
        t.join(30)
    done.set()
    threads[0].join(5)
    assert set(results) == set(honest), "an honest node did not finish"
    assert all(stats[i].rounds_done == rounds for i in honest)
    return stats


def hostile_pair(says, silent_after=1.0, rounds=5):
    """Nodes 0 and 1 run ``rounds`` rounds of a triangle whose third member (2) only sends what
    ``says(round)`` gives; their stats."""
    return team_with_member({0: {1, 2}, 1: {0, 2}, 2: {0, 1}}, 2, says, lambda i: silent_after, rounds=rounds,
                            init=lambda i: np.linspace(1, 2, 8) + 0.01 * i, resend_after=0.2,
                            check_state=lambda theirs, own: implausible(theirs, own, 0.5))


def test_a_member_that_sends_only_far_future_states_is_silent_and_left_out(caplog):
    """States of rounds far ahead (and RoundCompletes without a State) are no step forward: the
    member is left out as silent, its States counted as refused, and the others finish."""

    def says(_):
        return [Envelope("state", 2, r, np.linspace(1, 2, 8)) for r in range(50, 56)] + [
            Envelope("complete", 2, r) for r in range(56)]

    stats = hostile_pair(says)
    assert all(s.left_out == 1 and s.refused["far-future"] >= 1 for s in stats.values())
    assert "neighbour 2 has been silent" in caplog.text


def test_a_member_that_repeats_its_state_without_a_round_complete_is_left_out(caplog):
    """A member whose State of round 0 comes again and again, never with a RoundComplete, is
    left out once COMPLETE_WAIT x silent_after has passed without one; the others finish."""

    stats = hostile_pair(lambda _: [Envelope("state", 2, 0, np.linspace(1, 2, 8) + 0.02)])
    assert all(s.left_out == 1 for s in stats.values())
    assert "neighbour 2 sent its State of round 0 but no RoundComplete" in caplog.text


def test_on_a_ring_the_wait_for_a_silent_member_does_not_spread_to_the_next_hop(caplog):
    """A ring of five whose member 1 is silent (RoundCompletes, never a State): its neighbours 0
    and 2 wait silent_after for it, and their other neighbours (4 and 3), which have gone on to
    the next round meanwhile, wait for them rather than leave them out (they owe the RoundComplete
    of a State taken). Node 0 gives up on member 1 a little later than node 2 (its check came
    later): by then node 4 has gone on to round 1 and waits for node 0's State of it. Every honest
    node finishes and only member 1 is ever left out."""
    ring = {i: {(i - 1) % 5, (i + 1) % 5} for i in range(5)}
    stats = team_with_member(ring, 1, lambda r: [Envelope("complete", 1, r)], lambda i: 1.3 if i == 0 else 1.0)
    assert {i: s.left_out for i, s in stats.items()} == {0: 1, 2: 1, 3: 0, 4: 0}, caplog.text


def test_a_node_that_moves_on_after_a_long_wait_does_not_leave_out_its_waiting_neighbours(caplog):
    """A complete graph of five whose member 4 repeats its State of round 0 and never completes:
    every honest node waits COMPLETE_WAIT x silent_after for its RoundComplete, then goes on to
    round 1 and waits for the others' States of round 1 while their last word (their
    RoundComplete of round 0) is that long ago (here their States of round 1 reach node 0 0.7 s
    late: a busy host, a slow link): a neighbour that completed a round gets NEXT_STATE_WAIT x
    silent_after for its next State, so only member 4 is ever left out."""
    graph = {i: set(range(5)) - {i} for i in range(5)}
    late = lambda sender, receiver, env: 0.7 if (receiver, env.kind, env.round) == (0, "state", 1) else 0.0  # noqa: E731
    stats = team_with_member(graph, 4, lambda r: [Envelope("state", 4, 0, np.full(4, 2.0))], lambda i: 1.0, late)
    assert {i: s.left_out for i, s in stats.items()} == dict.fromkeys(range(4), 1), caplog.text
    assert "neighbour 4 sent its State of round 0 but no RoundComplete" in caplog.text


def run_clocked(graph, rounds, init, every_s, round_s=0.005, **kw):
    """run_timed for every node of ``graph`` in threads; each round takes ``round_s`` of compute
    (``rounds`` may be a dict: node -> its rounds). Returns results, stats, States sent per node."""
    sent: Counter[int] = Counter()

    def count(sender, receiver, env):
        if env.kind == "state" and receiver == min(graph[sender]):
            sent[sender] += 1
        return 0.0

    hub = MemoryHub(graph, count)
    stats = {i: ExchangeStats() for i in graph}

    def update(k, theta, fresh):
        threading.Event().wait(round_s)
        return (theta + sum(fresh.values())) / (1 + len(fresh))

    def node(i):
        n = rounds[i] if isinstance(rounds, dict) else rounds
        return run_timed(i, graph[i], n, init[i], update, hub.transport(i), every_s, stats=stats[i], linger=0.5, **kw)

    results, errors = in_threads(graph, node)
    assert not errors, errors
    return results, stats, sent


def test_on_a_clock_nodes_send_every_t_seconds_never_wait_and_still_agree():
    init = {i: np.full(4, 10.0 * i) for i in COMPLETE3}
    t0 = time.monotonic()
    results, stats, sent = run_clocked(COMPLETE3, 150, init, every_s=0.1)
    elapsed = time.monotonic() - t0
    for i in COMPLETE3:
        # A State before the first round, then one every 0.1 s while training, and the final one:
        # far fewer than one a round, and no round ever waited for a neighbour.
        assert 3 <= sent[i] <= elapsed / 0.1 + 3, (sent[i], elapsed)
        assert stats[i].rounds_done == 150
        assert set(stats[i].final_peers) == COMPLETE3[i]
    spread = np.ptp([results[i][0] for i in COMPLETE3])
    assert spread < 1.0, results  # from 0, 10 and 20: mixing what came made them agree


def test_on_a_clock_a_silent_neighbour_is_forgotten_and_the_others_go_on(caplog):
    forgotten = []
    init = {i: np.full(2, float(i)) for i in COMPLETE3}
    with caplog.at_level(logging.WARNING, logger="learner"):
        results, stats, _ = run_clocked(COMPLETE3, {0: 150, 1: 150, 2: 5}, init, every_s=0.05, silent_after=0.3,
                                        forget=forgotten.append)
    assert 2 in forgotten  # node 2 stopped after 5 rounds: 0 and 1 stopped pulling towards it
    assert "neighbour 2 has been silent" in caplog.text
    assert set(results) == {0, 1, 2} and stats[0].rounds_done == 150
    assert 2 not in stats[0].final_peers


def test_a_faulty_link_polled_without_waiting_still_delivers():
    from swarmmap.services.learner.faults import FaultyTransport
    from swarmmap.shared.run.config import FaultSettings

    hub = MemoryHub(COMPLETE3)
    link = FaultyTransport(hub.transport(0), 0, FaultSettings(link_success=1.0, duplicate=0.0))
    hub.transport(1).send_state(0, np.ones(3))
    msg = link.receive(timeout=0.0)
    assert msg is not None and msg.sender == 1 and link.receive(timeout=0.0) is None


def test_on_a_clock_states_near_the_team_pass_and_hostile_ones_are_refused():
    """The robots train apart between exchanges: a State far from this node's parameters but near
    another neighbour's newest passes; zeros, NaNs, a vector far from everyone, and States that
    grow 1.45 x an exchange, each near the sender's own last, are refused (a State never vouches
    for the next), and of a flood only each sender's newest is judged."""
    hub = MemoryHub(COMPLETE3)
    own = 1 + 0.1 * np.arange(8)
    near, apart = own + 0.2, own + 1.5  # node 2 near this node; node 2 then trained apart
    hostile = [np.zeros(8), np.full(8, np.nan), np.full(8, 40.0) + np.arange(8), 1.45 ** 4 * own]
    growing = [1.45 ** k * own for k in range(1, 5)]  # node 1: each 1.45 x its last
    hub.transport(2).send_state(0, near)
    taken = []

    def update(k, theta, fresh):  # what arrives while round k trains is taken before round k + 1
        taken.extend((j, round(float(v[0]), 3)) for j, v in fresh.items())
        if k < len(hostile):
            for r in range(5):  # a flood: the newest counts
                hub.transport(1).send_state(10 * k + r, growing[k] if r == 4 else hostile[k])
        if k == 1:
            hub.transport(2).send_state(4, apart)
        if k == 2:
            hub.transport(1).send_state(50, apart + 0.05)  # far from this node, near node 2's newest: passes
        return theta

    stats = ExchangeStats()
    run_timed(0, {1, 2}, 5, own, update, hub.transport(0), 10.0, stats=stats, linger=0.0,
              check_state=lambda theirs, ref: implausible(theirs, ref, 0.5))
    # 1.45 x own is 0.45 of own's norm away and passes once; 1.45^2 x own does not, near as it lies to
    # the last (and far from everyone else); node 1's State near node 2's newest passes.
    assert taken == [(2, 1.2), (1, 1.45), (2, 2.5), (1, 2.55)], taken
    assert stats.refused["implausible"] == 1, stats.refused  # (its last, older than one taken, is only ignored)


def test_on_a_clock_a_neighbour_that_says_two_things_for_one_round_is_left_out():
    """Two different plausible States of one round, back to back: the sender is banned for the
    run (neither is taken, nor anything it sends later); an honest neighbour's resend, the same
    State again, is no lie."""
    hub = MemoryHub(COMPLETE3)
    own = 1 + 0.1 * np.arange(8)
    taken = []

    def update(k, theta, fresh):
        taken.extend((k, j) for j in fresh)
        if k == 0:
            hub.transport(1).send_state(3, own + 0.01)
            hub.transport(1).send_state(3, own - 0.02)  # another State for its round 3
            hub.transport(2).send_state(3, own + 0.03)
            hub.transport(2).send_state(3, own + 0.03)  # the same again
        if k == 1:
            hub.transport(1).send_state(4, own)  # never heard again
        return theta

    stats = ExchangeStats()
    run_timed(0, {1, 2}, 4, own, update, hub.transport(0), 10.0, stats=stats, linger=0.0,
              check_state=lambda theirs, ref: implausible(theirs, ref, 0.5))
    assert taken == [(1, 2)] and stats.refused["equivocation"] == 1, (taken, stats.refused)


def test_the_inbox_bounds_what_one_neighbour_can_queue_and_never_holds_another_back():
    """A member flooding its link fills only its own share of the inbox: its further messages
    are dropped and counted, an honest neighbour's still come through, and once the node has
    taken what waited, the flooder's next message is queued again."""

    inbox = Inbox(per_sender=8)
    flood = [inbox.put(Envelope("state", 1, r, np.zeros(4, np.float32))) for r in range(1000)]
    assert sum(flood) == 8 and inbox.dropped[1] == 992
    assert inbox.put(Envelope("complete", 2, 0))
    got = [inbox.get(0.1) for _ in range(9)]
    assert [e.sender for e in got] == [1] * 8 + [2] and [e.round for e in got[:8]] == list(range(8))
    assert inbox.get(0.01) is None
    assert inbox.put(Envelope("state", 1, 1000)) and inbox.get(0.1).round == 1000


def test_a_neighbour_that_says_two_things_for_one_round_is_left_out_for_good(caplog):
    """Node 2 sends, for every round, its State and a second, different but plausible one: the
    others ban it at its first lie, finish without it, and their duplicates (honest resends, equal)
    ban nobody."""
    graph = COMPLETE3
    hub = MemoryHub(graph)
    init = {i: np.linspace(1, 2, 8) + 0.01 * i for i in graph}

    class Equivocating:
        def __init__(self, inner):
            self.inner = inner

        def new_state(self, n):
            return np.empty(n)

        def send_state(self, round, params):
            self.inner.send_state(round, params)
            self.inner.send_state(round, params * 1.01)  # plausible, and another word

        def __getattr__(self, name):
            return getattr(self.inner, name)

    stats = {i: ExchangeStats() for i in graph}
    transports = {0: hub.transport(0), 1: hub.transport(1), 2: Equivocating(hub.transport(2))}
    results, errors = in_threads(graph, lambda i: run_algorithm1(
        i, graph[i], 6, init[i], mixing_update(i), transports[i], resend_after=0.2, linger=0.3, stats=stats[i],
        peer_timeout=20, check_state=lambda theirs, own: implausible(theirs, own, 0.5)))
    assert not errors and set(results) == {0, 1, 2}
    assert stats[0].refused["equivocation"] == 1 and stats[1].refused["equivocation"] == 1
    assert stats[2].refused["equivocation"] == 0  # nobody honest is taken for a liar
    assert "sent two different States for round 0" in caplog.text


def test_a_neighbour_that_completes_rounds_without_sending_its_state_is_left_out_as_silent(caplog):
    """A stall: node 2's RoundCompletes come, its States never do. It counts as silent: after
    silent_after the others leave it out and finish."""
    graph = COMPLETE3
    hub = MemoryHub(graph)
    done = threading.Event()

    def staller():
        while not done.is_set():
            for r in range(6):
                for q in (0, 1):
                    hub.queues[q].put(Envelope("complete", 2, r))
            done.wait(0.05)

    init = {i: np.linspace(1, 2, 8) + 0.01 * i for i in (0, 1)}
    stats, results = {0: ExchangeStats(), 1: ExchangeStats()}, {}

    def node(i):
        results[i] = run_algorithm1(i, graph[i], 5, init[i], mixing_update(i), hub.transport(i), resend_after=0.2,
                                    linger=0.2, stats=stats[i], silent_after=1.0, peer_timeout=20)

    threads = [threading.Thread(target=staller)] + [threading.Thread(target=node, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads[1:]:
        t.join(30)
    done.set()
    threads[0].join(5)
    assert set(results) == {0, 1} and all(s.left_out >= 1 for s in stats.values())
    assert "neighbour 2 has been silent" in caplog.text


def test_a_lone_state_from_far_ahead_does_not_take_a_resumed_node_to_the_end():
    """A node resumed at round 2 of 40 with three neighbours: one State of round 40 (the end) is
    refused as far-future; once two neighbours say round 20, it jumps there (and no further)."""
    graph = {0: {1, 2, 3}, 1: {0}, 2: {0}, 3: {0}}
    hub = MemoryHub(graph)
    own = np.linspace(1, 2, 8)
    hub.queues[0].put(Envelope("state", 1, 40, own + 0.01))  # the end, from one neighbour only
    stats, rounds_seen = ExchangeStats(), []
    stop = threading.Event()

    def update(k, theta, peers):
        rounds_seen.append(k)
        stop.set()  # one update is enough: where did it jump to?
        return theta

    def feed():
        threading.Event().wait(0.3)
        hub.queues[0].put(Envelope("state", 2, 20, own + 0.02))
        hub.queues[0].put(Envelope("state", 3, 20, own + 0.03))

    threading.Thread(target=feed, daemon=True).start()
    with pytest.raises(InterruptedError):
        run_algorithm1(0, graph[0], 40, own, update, hub.transport(0), start_round=2, resumed=True, stats=stats,
                       keep_rounds=4, resend_after=5.0, stop=stop, peer_timeout=20,
                       check_state=lambda theirs, ref: implausible(theirs, ref, 0.5))
    assert rounds_seen == [20] and stats.caught_up == 1 and stats.refused["far-future"] >= 1


def test_a_node_far_more_rounds_behind_than_a_reunion_goes_on_from_its_teams_state():
    """A node that waited alone through a partition catches up 78 rounds: its own parameters are
    of round 2, its team's of round 80; it goes on from theirs (a few rounds behind: its own)."""
    graph = {0: {2, 3}, 2: {0}, 3: {0}}
    own = np.linspace(1, 2, 8)
    for start, target, expect in ((2, 80, own + 0.03), (40, 80, own)):
        hub, seen, stop = MemoryHub(graph), [], threading.Event()

        def update(k, theta, peers, seen=seen, stop=stop):
            seen.append((k, theta.copy()))
            stop.set()
            return theta

        def feed(hub=hub, target=target):
            threading.Event().wait(0.3)
            hub.queues[0].put(Envelope("state", 2, target, own + 0.02))
            hub.queues[0].put(Envelope("state", 3, target, own + 0.03))

        threading.Thread(target=feed, daemon=True).start()
        with pytest.raises(InterruptedError):
            run_algorithm1(0, graph[0], 100, own, update, hub.transport(0), start_round=start, resumed=True,
                           keep_rounds=4, resend_after=5.0, stop=stop, peer_timeout=20,
                           check_state=lambda theirs, ref: implausible(theirs, ref, 0.5))
        assert [k for k, _ in seen] == [target]
        np.testing.assert_array_equal(seen[0][1], expect)


def test_a_resumed_node_far_behind_its_team_judges_their_states_loosely_and_jumps():
    """Resumed at round 2 of 40, its parameters far from the team's (0.8 of their norm: beyond the
    plain check's 0.5); two neighbours vouch for round 20 and it jumps there, judging their States
    against its own parameters more loosely (check_stale). With one of its two neighbours gone,
    the other's word is enough."""
    own = np.linspace(1, 2, 8)
    team = own + 0.8 * np.linalg.norm(own) / np.sqrt(8)
    for gone in (False, True):
        graph = {0: {1, 2}, 1: {0}, 2: {0}}
        hub = MemoryHub(graph)
        hub.queues[0].put(Envelope("state", 1, 20, team))
        if gone:
            hub.lost.add(2)
        else:
            hub.queues[0].put(Envelope("state", 2, 20, team + 0.01))
        stats, seen = ExchangeStats(), []
        stop = threading.Event()

        def update(k, theta, peers):
            seen.append(k)
            stop.set()
            return theta

        def resend():  # the neighbours say their round again until heard (a lone word is not enough at first)
            while not stop.wait(0.6):
                hub.queues[0].put(Envelope("state", 1, 20, team))

        threading.Thread(target=resend, daemon=True).start()
        with pytest.raises(InterruptedError):
            run_algorithm1(0, graph[0], 40, own, update, hub.transport(0), start_round=2, resumed=True, stats=stats,
                           keep_rounds=4, resend_after=5.0, stop=stop, peer_timeout=20, rejoin_wait=0.0,
                           check_state=lambda theirs, ref: implausible(theirs, ref, 0.5),
                           check_stale=lambda theirs, ref: implausible(theirs, ref, 2.0))
        assert seen == [20] and stats.caught_up == 1, (gone, seen, stats)


def test_a_compressed_chains_second_word_for_a_round_is_no_lie():
    """A State of a compressed chain sent again after a replay decodes differently: it is not
    taken for equivocation (only States that repeat themselves exactly are compared)."""
    graph = {0: {1}, 1: {0}}
    hub = MemoryHub(graph)
    own = np.linspace(1, 2, 8)
    hub.queues[0].put(Envelope("state", 1, 0, own + 0.01, exact=False))
    hub.queues[0].put(Envelope("state", 1, 0, own + 0.02, exact=False))  # the same round, re-encoded
    hub.queues[0].put(Envelope("complete", 1, 0))
    stats = ExchangeStats()
    run_algorithm1(0, graph[0], 1, own, mixing_update(0), hub.transport(0), stats=stats, linger=0.1, peer_timeout=5,
                   check_state=lambda theirs, ref: implausible(theirs, ref, 0.5))
    assert stats.refused["equivocation"] == 0 and stats.rounds_done == 1


def test_a_round_without_progress_is_resent_less_and_less_often():
    """A round that does not move (a link too slow for its messages) is sent again after
    resend_after, then twice as long each time up to 8 times it, not every resend_after: the copies
    would fill the slow link further. Progress starts the count afresh."""
    hub = MemoryHub({0: {1}, 1: {0}})
    sent = []
    transport = hub.transport(0)
    send_state = transport.send_state
    transport.send_state = lambda k, s: (sent.append(k), send_state(k, s))
    machine = Algorithm1(0, {1}, lambda k, th, p: th, transport, ExchangeRules(resend_after=1.0, silent_after=1e6))
    loop = RoundLoop(machine)
    machine.begin(np.zeros(2), 10, 0, False)
    t0 = loop.last_progress
    resent_at = []
    for tick in range(1, 200):  # every half second for 100 s
        before = machine.stats.resends
        loop.housekeeping(t0 + tick / 2)
        if machine.stats.resends > before:
            resent_at.append(tick / 2)
    gaps = [b - a for a, b in zip([0.0, *resent_at], resent_at)]
    assert gaps[:5] == [1.5, 2.5, 4.5, 8.5, 8.5], gaps  # after > 1, > 2, > 4, then > 8 s, on half-second checks
    assert len(sent) == len(resent_at) and len(resent_at) <= 15  # 199 checks without the backoff: 66 copies
    loop.progress()
    assert loop.resend_wait == 1.0


def test_a_neighbour_behind_is_sent_its_rounds_again_less_and_less_often():
    """A neighbour behind at round 1 (on a slow link, it keeps saying so) is sent rounds 1-2
    again when it is still there after resend_after, then after more than 2, 4 and (up to 8 times
    resend_after) 8 s."""
    hub = MemoryHub({0: {1}, 1: {0}})
    replay = Replay(0, keep_rounds=4, resend_after=1.0, stats=ExchangeStats())
    for r in range(3):
        replay.remember(r, np.full(2, float(r)))
    times = []
    for t in range(0, 60):
        before = replay.stats.replayed
        replay.answer(1, 1, 2, hub.transport(0), t / 2)
        if replay.stats.replayed > before:
            times.append(t / 2)
    assert times == [1.5, 4.0, 8.5, 17.0, 25.5], times
