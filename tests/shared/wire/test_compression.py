"""Compressed States: each encoding's round trip through the wire codec, top-k's error feedback
and key frames, and what a receiver does with a chain it cannot follow."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from swarmmap.shared.wire.codec import decode, encode
from swarmmap.shared.wire.compression import Decompressor, compressor, deflate_codes, from_bf16_bits, inflate_codes, quantise, to_bf16_bits
from swarmmap.shared.wire.protocol import ProtocolError, State, StateBody, Tensor

RUN = "run-c"


def wire(body: StateBody, sender: int = 1, round: int = 0) -> tuple[State, int]:
    """A State with this body, through the codec: the decoded message and its size."""
    payload = encode(body.state(RUN, sender, round))
    return decode(payload, State, run=RUN, sender=sender), len(payload)


def vectors(n: int = 10_000, steps: int = 30, seed: int = 0):
    """A drifting parameter vector, as a learner's States are."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal(n).astype(np.float32)
    for _ in range(steps):
        v = v + rng.standard_normal(n).astype(np.float32) * 0.01
        yield v


@pytest.mark.parametrize("mode, tol, ratio", [("f16", 1e-3, 1.9), ("bf16", 8e-3, 1.9)])
def test_half_precisions_round_trip_within_their_precision_at_half_the_bytes(mode, tol, ratio):
    v = next(vectors())
    plain = len(encode(State(run=RUN, sender=1, round=0, params=Tensor.of(v))))
    msg, size = wire(compressor(mode).body(v))
    back = Decompressor().vector(msg)
    assert back.dtype == np.float32 and back.shape == v.shape
    np.testing.assert_allclose(back, v, rtol=tol, atol=1e-6)
    assert plain / size > ratio


def test_bf16_rounds_to_nearest_even():
    v = np.array([1.0, 1.0 + 2**-8, 1.0 + 3 * 2**-8, -2.5, 3.0e38], np.float32)
    back = from_bf16_bits(to_bf16_bits(v))
    assert back.tolist() == [1.0, 1.0, 1.0 + 2**-6, -2.5, pytest.approx(3.0e38, rel=1e-2)]


def test_f16_sends_float32_when_values_exceed_half_precision(caplog):
    v = np.array([1.0, 1e6], np.float32)
    fields = compressor("f16").body(v)
    assert fields.encoding == "f32" and "beyond half precision" in caplog.text
    assert Decompressor().vector(wire(fields)[0]).tolist() == [1.0, 1e6]


MATRICES = [(0, 50, 80), (4000, 100, 40), (8000, 40, 45)]  # three weight matrices of a 10,000-value vector


@pytest.mark.parametrize("mode", ["topk", "sign", "quant", "lowrank"])
def test_receivers_hold_exactly_the_senders_replica_and_the_error_feeds_back(mode):
    c, d = compressor(mode, density=0.02, keyframe_every=1000, rank=2, matrices=MATRICES), Decompressor()
    sent = 0
    for v in vectors():
        back = d.vector(wire(c.body(v))[0])
        np.testing.assert_array_equal(back, c.replica)  # bit for bit: both add the same float32 values
        sent += 1
    assert sent == 30
    # What the States left out stays owed, not lost: with the vector held still, the replica closes in.
    gap = np.abs(back - v).max()
    for _ in range(60):
        back = d.vector(wire(c.body(v))[0])
    if mode == "topk":
        np.testing.assert_allclose(back, v, atol=1e-6)
    elif mode == "quant":  # each State takes a third of what is still owed, or more: the copy converges
        np.testing.assert_allclose(back, v, atol=1e-5)
    elif mode == "lowrank":  # each power iteration takes the largest of what is owed: the copy closes in
        assert np.abs(back - v).max() < 0.5 * gap
    else:  # each sign step moves every value by its run's mean gap: it closes in, then dithers at a tiny scale
        assert np.abs(back - v).max() < gap and np.abs(back - v).mean() < 2e-3


@pytest.mark.parametrize("mode, density, ratio", [("topk", 0.04, 10), ("sign", 0.01, 20), ("quant", 0, 10)])
def test_chained_modes_send_a_tenth_of_the_bytes_or_less(mode, density, ratio):
    c = compressor(mode, density=density or 0.01, keyframe_every=100, bits=3)
    plain = compressed = 0
    for v in vectors(steps=100):
        plain += len(encode(State(run=RUN, sender=1, round=0, params=Tensor.of(v))))
        compressed += wire(c.body(v))[1]
    assert plain / compressed > ratio


def test_lowrank_carries_low_rank_drift_whole_at_about_a_tenth_of_the_bytes():
    """A layer's gradient steps are sums of a few outer products: rank-2 factors carry such drift
    (and the biases between matrices go whole), so the receivers' copy stays within float
    rounding of the vector."""
    rng = np.random.default_rng(3)
    v = rng.standard_normal(10_000).astype(np.float32)
    c, d = compressor("lowrank", keyframe_every=100, rank=2, matrices=MATRICES), Decompressor()
    plain = compressed = 0
    for step in range(100):
        for offset, rows, cols in MATRICES:
            u, w = rng.standard_normal((rows, 2)), rng.standard_normal((cols, 2))
            v[offset : offset + rows * cols] += (0.01 * u @ w.T).astype(np.float32).reshape(-1)
        v[9900:9910] += 0.01  # biases (no block covers them)
        fields = c.body(v)
        back = d.vector(wire(fields)[0])
        plain += len(encode(State(run=RUN, sender=1, round=0, params=Tensor.of(v))))
        compressed += wire(fields)[1]
        if step:
            assert fields.encoding == "lowrank" and [b[3] for b in fields.blocks] == [2, 2, 2]
    np.testing.assert_array_equal(back, c.replica)
    np.testing.assert_allclose(back, v, atol=1e-3)
    assert plain / compressed > 8  # (9.7: 910 values a State instead of 10,000, and a key frame)


@pytest.mark.parametrize("blocks, why", [
    ([[0, 4, 5, 1], [10, 4, 5, 1]], "overlaps another"),
    ([[0, 4, 5, 1], [20, 4, 5, 1]], "runs past size"),
    ([[0, 4, 5, 0]], "rank outside"),
    ([[0, 4, 5, 5]], "rank outside"),
    ([[0, 4, 5, 2]], "needs 28 values"),
])
def test_hostile_lowrank_states_are_refused(blocks, why):
    fields = {"encoding": "lowrank", "params": Tensor.of(np.ones(19, np.float32)), "size": 30, "seq": 1, "base": 0,
              "blocks": [[0, 4, 5, 1]]}
    doc = State(run=RUN, sender=1, round=0, **fields).model_dump(mode="python", exclude_none=True)
    doc["blocks"] = blocks
    import msgpack

    with pytest.raises(ProtocolError, match=why):
        decode(msgpack.packb(doc, use_bin_type=True), State, run=RUN)


def test_a_receiver_that_missed_an_update_waits_for_the_next_key_frame():
    c, d = compressor("topk", density=0.05, keyframe_every=5), Decompressor()
    states = [wire(c.body(v))[0] for v in vectors(steps=12)]
    assert [s.encoding for s in states[:6]] == ["f32", "topk", "topk", "topk", "topk", "f32"]
    assert d.vector(states[0]) is not None and d.vector(states[1]) is not None
    # states[2] is lost: 3 and 4 cannot be rebuilt, and the receiver says why
    assert d.vector(states[3]) is None and "waiting for its next key frame" in d.why
    assert d.vector(states[4]) is None and d.broken == 2
    np.testing.assert_array_equal(d.vector(states[5]), states[5].params.numpy())
    assert d.vector(states[6]) is not None


def test_a_key_frame_on_demand_starts_the_chain_again():
    c, d = compressor("topk", density=0.05, keyframe_every=100), Decompressor()
    vs = list(vectors(steps=4))
    for v in vs[:3]:
        d.vector(wire(c.body(v))[0])
    again = wire(c.body(vs[0], keyframe=True))[0]  # a State of an older round, sent again
    assert again.encoding == "f32" and again.seq is not None
    fresh = Decompressor()  # a neighbour that restarted
    np.testing.assert_array_equal(fresh.vector(again), vs[0])
    np.testing.assert_array_equal(d.vector(again), vs[0])  # the others start again from it too
    nxt = wire(c.body(vs[3]))[0]
    np.testing.assert_array_equal(fresh.vector(nxt), d.vector(nxt))


@pytest.mark.parametrize("bits", [*range(2, 9), 12, 16])
def test_quant_codes_pack_and_come_back_within_half_a_step(bits):
    rng = np.random.default_rng(bits)
    v = (rng.standard_normal(1024) * np.repeat([1e-4, 1.0, 30.0, 0.0], 256)).astype(np.float32)  # runs of any scale
    codes, steps = quantise(v, bits)
    assert codes.max() <= 2 ** bits - 2 and steps.shape == (4,) and steps[3] == 0
    np.testing.assert_array_equal(inflate_codes(deflate_codes(codes), v.size, bits), codes)
    c, d = compressor("quant", keyframe_every=100, bits=bits), Decompressor()
    d.vector(wire(c.body(np.zeros_like(v)))[0])  # the key frame
    back = d.vector(wire(c.body(v))[0])
    np.testing.assert_array_equal(back, c.replica)
    run_max = np.abs(v).reshape(4, 256).max(1)
    assert (np.abs(back - v).reshape(4, 256).max(1) <= run_max / (2 ** bits - 2) * 1.0001).all()


def test_a_quant_key_frame_starts_anywhere_and_a_missed_update_waits_for_the_next():
    c = compressor("quant", keyframe_every=4, bits=3)
    vs = list(vectors(steps=9))
    states = [wire(c.body(v))[0] for v in vs]
    assert [s.base for s in states[:5]] == [None, 0, 1, 2, None] and states[0].bits == 16 and states[1].bits == 3
    late = Decompressor()  # joins at the second key frame
    assert late.vector(states[3]) is None and "waiting for its next key frame" in late.why
    np.testing.assert_allclose(late.vector(states[4]), vs[4], atol=np.abs(vs[4]).max() / 65534 * 1.0001)
    np.testing.assert_array_equal(late.vector(states[5]), c.replica if len(states) == 6 else late.replicas[1][1])


def tensor(values: np.ndarray) -> dict:
    return {"dtype": values.dtype.str, "shape": list(values.shape), "data": values.tobytes()}


@pytest.mark.parametrize("change, why", [
    (lambda f: f.update(indices=tensor(np.array([3, 3, 7], np.uint32))), "increase strictly"),
    (lambda f: f.update(indices=tensor(np.array([3, 5, 99], np.uint32))), "below size"),
    (lambda f: f.update(params=tensor(np.array([1, np.inf, 2], np.float32))), "non-finite"),
    (lambda f: f.pop("base"), "needs size, seq and base"),
])
def test_hostile_topk_states_are_refused(change, why):
    fields = {"encoding": "topk", "params": Tensor.of(np.ones(3, np.float32)), "size": 10, "seq": 1, "base": 0,
              "indices": Tensor.of(np.array([1, 4, 9], np.uint32))}
    doc = State(run=RUN, sender=1, round=0, **fields).model_dump(mode="python", exclude_none=True)
    change(doc)
    import msgpack

    with pytest.raises(ProtocolError, match=why):
        decode(msgpack.packb(doc, use_bin_type=True), State, run=RUN)


@pytest.mark.parametrize("change, why", [
    (lambda f: f.pop("bits"), "bits belong to quant States"),
    (lambda f: f.update(bits=17), "less than or equal to 16"),
    (lambda f: f.update(scales=tensor(np.array([1, 2], np.float32))), "needs 1 scales"),
    (lambda f: f.update(scales=tensor(np.array([np.nan], np.float32))), "non-finite"),
])
def test_hostile_quant_states_are_refused(change, why):
    fields = compressor("quant", bits=3).body(np.ones(10, np.float32))
    doc = fields.state(RUN, 1, 0).model_dump(mode="python", exclude_none=True)
    change(doc)
    import msgpack

    with pytest.raises(ProtocolError, match=why):
        decode(msgpack.packb(doc, use_bin_type=True), State, run=RUN)


@pytest.mark.parametrize("stream, why", [
    (np.frombuffer(b"not deflate at all", np.uint8), "not a deflate stream"),
    (deflate_codes(np.zeros(9, np.uint8)), "exactly 10 codes"),
    (deflate_codes(np.zeros(11, np.uint8)), "exactly 10 codes"),
    (deflate_codes(np.zeros(10_000_000, np.uint8)), "exactly 10 codes"),  # a bomb: inflated no further than 10
    (deflate_codes(np.full(10, 8, np.uint8)), "beyond 3 bits"),
])
def test_a_quant_state_whose_codes_do_not_inflate_to_its_size_is_refused_by_the_receiver(stream, why):
    c, d = compressor("quant", bits=3), Decompressor()
    d.vector(wire(c.body(np.ones(10, np.float32)))[0])
    good = c.body(np.full(10, 2, np.float32))
    bad = wire(dataclasses.replace(good, params=Tensor.of(stream, "|u1")))[0]
    assert d.vector(bad) is None and why in d.why and "quant State 1 of node 1 is refused" in d.why
    assert d.vector(wire(good)[0]) is not None  # a resend of the good one still adds to the chain


def test_an_empty_quant_state_cannot_carry_a_bomb():
    with pytest.raises(ValueError, match="exactly 0 codes"):
        inflate_codes(deflate_codes(np.zeros(10_000_000, np.uint8)), 0, 3)
    assert inflate_codes(deflate_codes(np.zeros(0, np.uint8)), 0, 3).size == 0


def test_non_finite_bf16_bits_are_refused():
    bits = to_bf16_bits(np.array([1.0, np.inf], np.float32))
    with pytest.raises(ValueError, match="non-finite"):
        State(run=RUN, sender=1, round=0, encoding="bf16", params=Tensor.of(bits, "<u2"))
