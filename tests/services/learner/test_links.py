"""Algorithm 1 on poor and thin links: States through the wire codec in process, compressed,
exchanged every few rounds, and rounds that go on without the States that do not come."""

from __future__ import annotations

import time

import numpy as np
import pytest

from swarmmap.services.learner import pace as pace_module
from swarmmap.services.learner.codec import StateCodec
from swarmmap.services.learner.exchange import ExchangeStats
from swarmmap.services.learner.faults import FaultyTransport
from swarmmap.services.learner.memory_link import MemoryLink
from swarmmap.services.learner.pace import Pace
from swarmmap.services.learner.transport import MemoryHub
from swarmmap.shared.run.config import FaultSettings
from swarmmap.shared.wire.compression import compressor

from .test_algorithm1 import COMPLETE3, in_threads, mixing_update, reference, run_algorithm1


def run_wire(graph, rounds, init, *, compression="none", density=0.01, every=1, faults=None, round_wait=0.0,
             update=mixing_update, timeout=60, paces=None):
    """Every node in a thread, its States through the wire codec (counted), encoded and numbered
    by a StateCodec; returns results, stats, the hub and what each node put on the wire. With
    ``paces`` (a dict, filled with each node's :class:`Pace`) a node whose links set the pace
    switches its States to quant, as a learner does."""
    hub = MemoryHub(graph, run="links")
    wire_rounds: dict[int, list[int]] = {i: [] for i in graph}
    stats = {i: ExchangeStats() for i in graph}

    def node(i):
        inner = MemoryLink(hub, i)
        spy_send, spy_body = inner.send_state, inner.send_body
        inner.send_state = lambda r, p: (wire_rounds[i].append(r), spy_send(r, p))
        inner.send_body = lambda r, b: (wire_rounds[i].append(r), spy_body(r, b))
        link = FaultyTransport(inner, i, faults) if faults is not None else inner
        codec = StateCodec(link, i, compressor(compression, density, keyframe_every=10), every)
        pace = None
        if paces is not None:
            pace = paces[i] = Pace(i, lambda: (setattr(codec, "compressor", compressor("quant", keyframe_every=10)), "quant")[1])
        return run_algorithm1(i, graph[i], rounds, init[i], update(i), codec, stats=stats[i], resend_after=0.2,
                              linger=0.5, round_wait=round_wait, peer_timeout=20, pace=pace)

    results, errors = in_threads(graph, node, timeout)
    assert not errors, errors
    return results, stats, hub, wire_rounds


def init_vectors(graph, n=4000):
    rng = np.random.default_rng(1)
    return {i: rng.standard_normal(n).astype(np.float32) for i in graph}


def test_states_through_the_wire_codec_in_process_give_the_reference_and_count_their_bytes():
    init = init_vectors(COMPLETE3)
    results, _, hub, _ = run_wire(COMPLETE3, 8, init)
    ref = reference(COMPLETE3, 8, init)
    for i in COMPLETE3:
        np.testing.assert_allclose(results[i], ref[i], rtol=1e-6)
    # 9 States (rounds 0..8) of 4000 float32 at least, and RoundCompletes, per node
    assert all(hub.bytes_sent[i] > 9 * 16_000 for i in COMPLETE3)
    assert all(hub.bytes_received[i] >= 2 * 9 * 16_000 for i in COMPLETE3)


def test_lossless_topk_is_the_reference_and_lossy_topk_sends_a_tenth():
    init = init_vectors(COMPLETE3)
    ref = reference(COMPLETE3, 8, init)
    exact, _, _, _ = run_wire(COMPLETE3, 8, init, compression="topk", density=1.0)
    for i in COMPLETE3:
        np.testing.assert_allclose(exact[i], ref[i], rtol=1e-5, atol=1e-6)
    plain = run_wire(COMPLETE3, 30, init)[2]
    thin = run_wire(COMPLETE3, 30, init, compression="topk", density=0.01)[2]
    assert sum(plain.bytes_sent.values()) / sum(thin.bytes_sent.values()) > 3  # RoundCompletes are not compressed
    states_plain = 31 * 16_000
    assert all(thin.bytes_sent[i] < states_plain / 5 for i in COMPLETE3)


def test_quant_states_keep_the_copies_close_behind_at_a_fifth_of_the_bytes():
    init = init_vectors(COMPLETE3)
    ref = reference(COMPLETE3, 30, init)
    plain = run_wire(COMPLETE3, 30, init)[2]
    results, _, quant, _ = run_wire(COMPLETE3, 30, init, compression="quant")
    # The mixing ends near where it would (values near 10), from 3-bit differences: within 2% here
    # alone, 6% on a loaded machine, where resends for older rounds (key frames) make later
    # differences larger. A wrong rebuild lands far off, a broken chain never ends.
    for i in COMPLETE3:
        np.testing.assert_allclose(results[i], ref[i], atol=1.0)
    assert all(plain.bytes_sent[i] / quant.bytes_sent[i] > 5 for i in COMPLETE3)  # RoundCompletes are not compressed


@pytest.mark.parametrize("mode", ["f16", "bf16"])
def test_half_precision_states_end_near_the_reference(mode):
    init = init_vectors(COMPLETE3)
    results, _, _, _ = run_wire(COMPLETE3, 8, init, compression=mode)
    ref = reference(COMPLETE3, 8, init)
    for i in COMPLETE3:
        np.testing.assert_allclose(results[i], ref[i], rtol=2e-2, atol=2e-2)


def test_a_node_whose_links_set_the_pace_compresses_its_states_and_its_neighbours_follow(monkeypatch, caplog):
    """Every message late by up to 0.12 s, rounds that compute in microseconds: each node waits far
    longer than it trains, switches its States to quant after a window of rounds and says so; its
    neighbours rebuild them (the mixing ends where it would) and fewer bytes go out."""
    monkeypatch.setattr(pace_module, "SLOW_WINDOW", 5)
    monkeypatch.setattr(pace_module, "SLOW_MIN_WAIT_S", 0.03)
    init = init_vectors(COMPLETE3)
    ref = reference(COMPLETE3, 30, init)
    paces = {}
    results, _, hub, _ = run_wire(COMPLETE3, 30, init, faults=FaultSettings(delay_s=0.12), paces=paces)
    plain = run_wire(COMPLETE3, 30, init)[2]
    for i in COMPLETE3:
        assert paces[i].adapted == "quant"
        np.testing.assert_allclose(results[i], ref[i], atol=1.0)
        assert plain.bytes_sent[i] / hub.bytes_sent[i] > 2
    assert caplog.text.count("its links, not its training, set the pace") == 3
    fast = {}
    results, _, _, _ = run_wire(COMPLETE3, 30, init, paces=fast)  # no delay: nobody switches
    assert all(p.adapted is None for p in fast.values())
    for i in COMPLETE3:
        np.testing.assert_allclose(results[i], ref[i], rtol=1e-6)


def test_the_pace_is_judged_on_medians_of_wait_against_training():
    switched = []
    pace = Pace(4, lambda: switched.append(1) or "quant")
    for r in range(1, 20):  # one long wait (a partition) among fast rounds is no slow link
        pace.round_done(r, 30.0 if r == 3 else 0.01, 0.05)
    pace.round_done(20, 0.01, 0.05)
    assert pace.adapted is None
    slow_trainer = Pace(4, lambda: "quant")  # waits of 0.4 s against 0.3 s of training: training sets the pace
    for r in range(1, 40):
        slow_trainer.round_done(r, 0.4, 0.3)
    assert slow_trainer.adapted is None
    for r in range(21, 41):  # then waits of 0.5 s against 0.05 s: the links set the pace, once
        pace.round_done(r, 0.5, 0.05)
    assert pace.adapted == "quant" and switched == [1]
    crawling = Pace(4, lambda: "quant")  # waits of a minute a round: judged after 3 rounds, not 20
    for r in range(1, 3):
        crawling.round_done(r, 60.0, 0.05)
    assert crawling.adapted is None
    crawling.round_done(3, 60.0, 0.05)
    assert crawling.adapted == "quant"
    never = Pace(4)  # no slow_link: a node that keeps its encoding
    for r in range(1, 40):
        never.round_done(r, 5.0, 0.05)
    assert never.adapted is None


def test_exchange_every_k_rounds_numbers_states_by_training_round():
    init = init_vectors(COMPLETE3, 16)
    results, stats, _, wire_rounds = run_wire(COMPLETE3, 4, init, every=5)  # 4 exchanges = 20 training rounds
    assert sorted(set(wire_rounds[0])) == [0, 5, 10, 15, 20]
    np.testing.assert_allclose(results[0], reference(COMPLETE3, 4, init)[0], rtol=1e-6)
    assert stats[0].rounds_done == 4


def test_on_a_dead_link_rounds_go_on_after_round_wait_without_leaving_anyone_out(caplog):
    """Node 2's messages never reach 0 and 1: with round_wait the rounds go on with the States
    that came, 2 is missing from every round of 0 and 1 but never left out, and 2 (which hears
    everyone) still gets their States."""
    faults = FaultSettings(link_success=1e-9, links=[[2, 0], [2, 1]])
    init = init_vectors(COMPLETE3, 16)
    t0 = time.monotonic()
    results, stats, _, _ = run_wire(COMPLETE3, 10, init, faults=faults, round_wait=0.1)
    assert time.monotonic() - t0 < 15  # not the 30 s a silent neighbour takes to be left out, let alone forever
    assert stats[0].missed >= 10 and stats[1].missed >= 10
    assert stats[0].left_out == stats[1].left_out == 0
    assert stats[2].missed < 10
    assert all(r.shape == (16,) and np.isfinite(r).all() for r in results.values())
    assert "left out" not in caplog.text and "goes on without it" not in caplog.text


def test_round_wait_changes_nothing_where_every_message_arrives():
    init = init_vectors(COMPLETE3, 16)
    results, stats, _, _ = run_wire(COMPLETE3, 10, init, round_wait=5.0)
    ref = reference(COMPLETE3, 10, init)
    for i in COMPLETE3:
        np.testing.assert_allclose(results[i], ref[i], rtol=1e-6)
        assert stats[i].missed == 0


def test_a_dynamic_disk_graph_hears_only_the_neighbours_in_range():
    """Robots 0 and 1 stand 3 m apart, robot 2 is 40 m away (radius 10 m): 0 and 1 exchange,
    2 trains alone, and the rounds never wait for the links out of range."""
    where = {0: (0.0, 0.0), 1: (3.0, 0.0), 2: (40.0, 0.0)}
    hub = MemoryHub(COMPLETE3, run="links")
    codecs = {i: StateCodec(MemoryLink(hub, i), i, radius=10.0, position=lambda i=i: where[i]) for i in COMPLETE3}
    seen: dict[int, set[int]] = {i: set() for i in COMPLETE3}

    def update(i):
        def step(k, theta, peers):
            seen[i] |= set(peers)
            return mixing_update(i)(k, theta, peers)
        return step

    init = init_vectors(COMPLETE3, 16)
    stats = {i: ExchangeStats() for i in COMPLETE3}
    results, _ = in_threads(COMPLETE3, lambda i: run_algorithm1(i, COMPLETE3[i], 6, init[i], update(i), codecs[i],
                                                                stats=stats[i], round_wait=0.1, resend_after=5,
                                                                linger=0.2), timeout=30)
    assert seen == {0: {1}, 1: {0}, 2: set()}
    assert codecs[2].ignored > 0 and codecs[0].ignored > 0
    assert len(results) == 3 and all(s.left_out == 0 for s in stats.values())


def test_a_link_down_for_a_round_is_down_both_ways_and_for_its_resends():
    """faults.per_round: one draw per link and round, the same at both ends, so a round's
    messages and their resends are all lost together, and the loss rate is link_success's."""
    from swarmmap.services.learner.transport import Envelope

    faults = FaultSettings(link_success=0.3, per_round=True, seed=4)
    hub = MemoryHub({0: {1}, 1: {0}})
    a, b = FaultyTransport(hub.transport(0), 0, faults), FaultyTransport(hub.transport(1), 1, faults)
    up_a = [a._link_up(Envelope("state", 1, r)) for r in range(400)]
    up_b = [b._link_up(Envelope("state", 0, r)) for r in range(400)]
    assert up_a == up_b  # both directions of the link agree, round by round
    assert up_a == [a._link_up(Envelope("complete", 1, r)) for r in range(400)]  # every message of the round
    assert 0.22 < sum(up_a) / 400 < 0.38


def test_states_carry_their_senders_coverage_and_a_foreign_grid_is_ignored(caplog):
    """With a Coverage, each State says which cells its sender knows to be covered; the receiver
    merges them once past the State's round (and passes them on in its own States), and still
    uses the parameters of a State
    whose coverage does not fit its grid, with one warning naming the sender."""
    from swarmmap.shared.wire.codec import encode
    from swarmmap.shared.wire.protocol import State, Tensor
    from swarmmap.shared.world.unseen import Coverage

    bounds = (0.0, 0.0, 6.0, 4.0)
    rng = np.random.default_rng(0)
    left = np.column_stack([rng.uniform(0, 2, 500), rng.uniform(0, 4, 500)])
    right = left + [4.0, 0.0]
    line = {0: {1}, 1: {0, 2}, 2: {1}}
    hub = MemoryHub(line, run="links")
    cover = {0: Coverage(bounds, 0.5, left), 1: Coverage(bounds, 0.5, np.zeros((0, 2))), 2: Coverage(bounds, 0.5, right)}
    codecs = {i: StateCodec(MemoryLink(hub, i), i, coverage=cover[i]) for i in line}
    vec = np.arange(8, dtype=np.float32)
    codecs[0].send_state(0, vec)
    codecs[2].send_state(0, vec)
    got = [codecs[1].receive(1.0) for _ in range(2)]
    assert all(e is not None and e.kind == "state" for e in got)
    assert not cover[1].covered().any()  # offered with round 0: taken in when robot 1 starts round 1
    assert cover[1].advance(1)
    np.testing.assert_array_equal(cover[1].covered(), cover[0].own | cover[2].own)
    codecs[1].send_state(1, vec)  # robot 1 has no data of its own but passes the team's on
    assert codecs[0].receive(1.0) is not None and cover[0].advance(2)
    np.testing.assert_array_equal(cover[0].covered(), cover[0].own | cover[2].own)
    before = cover[1].covered().copy()
    hub.queues[1].put(("state", encode(State(run="links", sender=0, round=2, params=Tensor.of(vec, "<f4"),
                                             coverage=Tensor.of(np.full(5, 255, np.uint8), "|u1")))))
    with caplog.at_level("WARNING"):
        env = codecs[1].receive(1.0)
    assert env is not None and env.round == 2
    np.testing.assert_array_equal(env.params, vec)
    cover[1].advance(3)
    np.testing.assert_array_equal(cover[1].covered(), before)
    assert "node 0's coverage ignored" in caplog.text
