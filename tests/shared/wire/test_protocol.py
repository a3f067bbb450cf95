"""The wire codec: round trips, and every kind of bad payload is refused with its reason."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from swarmmap.shared.wire.codec import STATE_ALIGN, StateFrame, all_finite, decode, encode, encode_state, wire_dict
from swarmmap.shared.wire.protocol import (
    MAX_GOAL_PATH,
    Goal,
    Keys,
    Metrics,
    ProtocolError,
    RoundComplete,
    Samples,
    Scan,
    State,
    Tensor,
    WorldMap,
)

RUN = "run-1"


def state(**over) -> State:
    fields = dict(run=RUN, sender=2, round=7, params=Tensor.of(np.arange(5, dtype=np.float32)))
    fields.update(over)
    return State(**fields)


def raw(message) -> dict:
    return wire_dict(message)


def test_state_round_trip_preserves_params_bit_for_bit():
    params = np.random.default_rng(0).standard_normal(1000).astype(np.float32)
    msg = State(run=RUN, sender=1, round=3, params=Tensor.of(params))
    back = decode(encode(msg), State, run=RUN, sender=1)
    assert back.round == 3 and back.sender == 1
    assert back.params.numpy().tobytes() == params.tobytes()


def test_tensor_bytes_are_little_endian_float32():
    t = Tensor.of(np.array([1.0], dtype=">f4"))
    assert t.dtype == "<f4" and t.data == np.float32(1.0).tobytes()  # this test machine is little-endian


@pytest.mark.parametrize("message", [
    RoundComplete(run=RUN, sender=0, round=0),
    Metrics(run=RUN, sender=1, round=5, wall_time_s=1.5, val_bce=0.3, consensus_error=0.01, bytes_sent=10,
            bytes_received=20, pid=42, final=True),
    Scan(run=RUN, sender=0, seq=1, t=0.5, pose=[1.0, 2.0, 0.1], max_range=3.5,
         angles=Tensor.of(np.zeros(4, np.float32)), ranges=Tensor.of(np.ones(4, np.float32)),
         hit=Tensor.of(np.ones(4, np.uint8))),
    Samples(run=RUN, sender=0, seq=1, t=0.5, position=[0.0, 0.0], points=Tensor.of(np.zeros((3, 2), np.float32)),
            labels=Tensor.of(np.array([0, 1, 0], np.float32)), last=True),
    WorldMap(run=RUN, sender=0, resolution=0.1, origin=[0.0, 0.0], grid=Tensor.of(np.eye(3, dtype=np.uint8)),
             val_points=Tensor.of(np.zeros((2, 2), np.float32)), val_labels=Tensor.of(np.zeros(2, np.float32)),
             robots=3),
    Goal(run=RUN, sender=1, leg=2, round=20, x=1.5, y=-2.0, path=Tensor.of(np.array([[0, 0], [1.5, -2]], np.float32)),
         reason="std 4.0 over 2.5 m"),
    Goal(run=RUN, sender=1, leg=3, round=30, done=True, reason="no uncertainty goal left"),
    Samples(run=RUN, sender=0, seq=4, t=0.8, position=[0.0, 0.0], points=Tensor.of(np.zeros((1, 2), np.float32)),
            labels=Tensor.of(np.zeros(1, np.float32)), leg=2, leg_end=True),
])
def test_every_message_kind_round_trips(message):
    assert decode(encode(message), type(message), run=RUN) == message


def refused(payload: bytes, expected=State, **kw) -> str:
    with pytest.raises(ProtocolError) as info:
        decode(payload, expected, run=kw.pop("run", RUN), **kw)
    return info.value.reason


def test_refuses_garbage():
    assert refused(b"\xc1\xff\x00not msgpack") == "malformed"
    assert refused(msgpack.packb([1, 2, 3])) == "malformed"


def test_refuses_oversized_before_decoding():
    assert refused(encode(state()), max_bytes=10) == "oversized"


def test_refuses_another_run():
    assert refused(encode(state()), run="other-run") == "wrong-run"


def test_refuses_sender_that_does_not_match_its_key():
    assert refused(encode(state(sender=2)), sender=3) == "unknown-sender"


def test_refuses_other_schema_version_and_kind():
    doc = raw(state())
    doc["v"] = 3
    assert refused(msgpack.packb(doc)) == "version"
    assert refused(encode(RoundComplete(run=RUN, sender=2, round=1))) == "kind"


def test_a_state_from_an_older_swarmmap_is_refused_saying_so():
    doc = raw(state())
    doc["v"] = 1
    with pytest.raises(ProtocolError, match="older swarmmap") as info:
        decode(msgpack.packb(doc), State, run=RUN)
    assert info.value.reason == "version"


def test_messages_whose_layout_did_not_change_are_read_at_version_1():
    """A recording made by the previous build holds Samples of schema version 1: still read."""
    msg = Samples(run=RUN, sender=0, seq=1, t=0.5, position=[0.0, 0.0], points=Tensor.of(np.zeros((3, 2), np.float32)),
                  labels=Tensor.of(np.array([0, 1, 0], np.float32)), last=True)
    doc = raw(msg)
    doc["v"] = 1
    assert decode(msgpack.packb(doc), Samples, run=RUN).points == msg.points


def test_refuses_wrong_dtype():
    doc = raw(state())
    doc["params"] = raw(Tensor.of(np.arange(5, dtype=np.float64)))
    assert refused(msgpack.packb(doc)) == "shape"


def test_refuses_wrong_shape():
    doc = raw(state())
    doc["params"] = raw(Tensor.of(np.zeros((2, 2), np.float32)))
    assert refused(msgpack.packb(doc)) == "shape"


def test_refuses_data_length_that_does_not_match_shape():
    doc = raw(state())
    doc["params"]["shape"] = [6]
    assert refused(msgpack.packb(doc)) == "shape"


def test_refuses_non_finite_params_and_values():
    doc = raw(state())
    doc["params"]["data"] = np.array([0, 1, np.nan, 3, 4], np.float32).tobytes()
    assert refused(msgpack.packb(doc)) == "non-finite"
    m = raw(Metrics(run=RUN, sender=1, round=5, wall_time_s=1.5, val_bce=0.3, consensus_error=0.0,
                    bytes_sent=0, bytes_received=0))
    m["val_bce"] = float("inf")
    assert refused(msgpack.packb(m), Metrics) == "non-finite"


def test_refuses_unknown_fields_and_pickle_like_extensions():
    doc = raw(state())
    doc["extra"] = 1
    assert refused(msgpack.packb(doc)) == "invalid"
    assert refused(msgpack.packb(msgpack.ExtType(1, b"x"))) == "malformed"


def test_refuses_labels_outside_unit_interval():
    s = Samples(run=RUN, sender=0, seq=0, t=0, position=[0, 0], points=Tensor.of(np.zeros((1, 2), np.float32)),
                labels=Tensor.of(np.zeros(1, np.float32)))
    doc = raw(s)
    doc["labels"] = raw(Tensor.of(np.array([2.0], np.float32)))
    assert refused(msgpack.packb(doc), Samples) == "invalid"


def test_keys_are_built_under_prefix_and_run_and_refuse_wildcards():
    keys = Keys("swarmmap", "r1")
    assert keys.state(3) == "swarmmap/r1/learners/3/state"
    assert keys.round_complete(3) == "swarmmap/r1/learners/3/round-complete"
    assert keys.samples(0) == "swarmmap/r1/robots/0/samples"
    assert keys.world_map() == "swarmmap/r1/world/map"
    assert keys.parse_alive(keys.alive("learner", 4)) == ("learner", "4")
    assert keys.ident_of(keys.metrics(12)) == 12
    for bad in ("a/b", "*", "$x", "**", ""):
        with pytest.raises(ValueError):
            Keys("swarmmap", bad)


@pytest.mark.parametrize("n", [0, 3, 70, 20000, 527361])
def test_state_fast_path_writes_and_reads_what_the_generic_codec_does(n):
    """Algorithm 1's hot path: encode_state writes the msgpack map any reader takes for the
    State, with its vector aligned in the payload, and decode takes it back without a copy,
    with the same fields and values."""
    params = np.random.default_rng(n).standard_normal(n).astype(np.float32)
    payload = encode_state("run-1", 3, 17, params)
    state = State(run="run-1", sender=3, round=17, params=Tensor.of(params, "<f4"))
    assert msgpack.unpackb(payload) == wire_dict(state)
    assert payload == encode(state)
    assert (len(payload) - params.nbytes) % STATE_ALIGN == 0, "the vector must start aligned"
    msg = decode(payload, State, run="run-1", sender=3)
    assert (msg.sender, msg.round, msg.params.shape) == (3, 17, [n])
    np.testing.assert_array_equal(msg.params.numpy(), params)
    assert encode(msg) == payload, "a decoded State must encode back to the same bytes"


def test_state_fast_path_refuses_what_the_generic_codec_refuses():
    params = np.ones(100, np.float32)
    good = encode_state("run-1", 3, 17, params)
    with pytest.raises(ProtocolError) as err:
        decode(good, State, run="run-2", sender=3)
    assert err.value.reason == "wrong-run"
    with pytest.raises(ProtocolError) as err:
        decode(good, State, run="run-1", sender=4)
    assert err.value.reason == "unknown-sender"
    bad = params.copy()
    bad[57] = np.nan
    with pytest.raises(ProtocolError) as err:
        decode(encode_state("run-1", 3, 17, bad), State, run="run-1", sender=3)
    assert err.value.reason == "non-finite"
    for cut in (1, 4, 399):  # truncated: the vector's length no longer matches its header
        with pytest.raises(ProtocolError):
            decode(good[:-cut], State, run="run-1", sender=3)
    with pytest.raises(ProtocolError):  # bytes appended after the vector
        decode(good + b"\x00\x00\x00\x00", State, run="run-1", sender=3)
    with pytest.raises(ProtocolError):  # the length field says more than is there
        decode(good.replace(b"\xc6\x00\x00\x01\x90", b"\xc6\x00\x00\x01\x94"), State, run="run-1", sender=3)
    with pytest.raises(ValueError):
        encode_state("bad run name", 3, 17, params)


def test_state_fast_path_takes_huge_finite_values_through_the_full_check():
    params = np.full(10, 3e38, np.float32)  # finite, but its dot product overflows
    msg = decode(encode_state("run-1", 0, 1, params), State, run="run-1", sender=0)
    np.testing.assert_array_equal(msg.params.numpy(), params)


@pytest.mark.parametrize("run", ["r", "run-1", "x" * 40, "y" * 64])
def test_a_state_frame_is_the_payload_of_encode_state_without_a_copy(run):
    """A learner writes its parameters into a StateFrame's vector; stamping a round makes the
    frame the exact payload encode_state writes, for any run name and any round."""
    values = np.random.default_rng(1).standard_normal(1000).astype(np.float32)
    vector = StateFrame.new(run, 42, values.size)
    vector[:] = values
    frame = StateFrame.of(vector)
    assert frame is not None
    for r in (0, 1, 200, 70000, 10**9):
        assert bytes(frame.stamp(r)) == encode_state(run, 42, r, values)
        msg = decode(bytes(frame), State, run=run, sender=42)
        assert msg.round == r
        np.testing.assert_array_equal(msg.params.numpy(), values)
    assert StateFrame.of(vector[1:]) is None and StateFrame.of(values) is None, "only a frame's whole vector is one"
    with pytest.raises(ValueError):
        frame.stamp(10**9 + 1)
    with pytest.raises(ValueError):
        StateFrame.new("bad run", 1, 10)


@pytest.mark.parametrize("n", [10, 5000, 527361])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_all_finite_finds_any_non_finite_value_and_takes_huge_finite_ones(n, bad):
    """The receivers' finiteness check (one summing pass where torch is loaded, numpy's mask
    otherwise) is exact: a sum that overflows is no reason to refuse."""
    import torch  # noqa: F401  (loaded, as in a learner: the summing pass)

    values = np.random.default_rng(n).standard_normal(n).astype(np.float32)
    assert all_finite(values)
    for at in (0, n // 2, n - 1):
        spoiled = values.copy()
        spoiled[at] = bad
        assert not all_finite(spoiled)
    huge = np.full(n, 3e38, np.float32)
    huge[::2] *= -1 if n % 2 else 1
    assert all_finite(huge)


def test_a_states_coverage_round_trips_and_a_bad_one_is_refused():
    bits = np.array([0b10100000, 255, 0], np.uint8)
    msg = State(run=RUN, sender=1, round=3, params=Tensor.of(np.arange(4, dtype=np.float32)), coverage=Tensor.of(bits, "|u1"))
    assert not msg.plain
    back = decode(encode(msg), State, run=RUN)
    np.testing.assert_array_equal(back.coverage.numpy(), bits)
    for bad in (Tensor.of(np.zeros(4, np.float32)), Tensor.of(np.zeros((2, 2), np.uint8), "|u1"),
                Tensor.of(np.zeros((1 << 20) + 1, np.uint8), "|u1")):
        doc = raw(msg)
        doc["coverage"] = raw(bad)
        assert refused(msgpack.packb(doc)) == "shape"


def bomb(kind: str, depth: int, width: int, **header) -> bytes:
    """A payload with a valid header of ``kind`` whose next field is ``width ** depth`` empty
    maps nested ``depth`` arrays deep (the object bomb: millions of objects in a few MB)."""
    head = {"v": 2, "kind": kind, "run": RUN, "sender": 2, **header}
    leaf = b"\x80"  # an empty map
    for _ in range(depth):
        leaf = b"\xdd" + width.to_bytes(4, "big") + leaf * width
    body = msgpack.packb(head)[1:]  # the header's entries, without their map's own header
    return b"\xde" + (len(head) + 1).to_bytes(2, "big") + body + msgpack.packb("params") + leaf


@pytest.mark.parametrize("kind,model", [("State", State), ("RoundComplete", RoundComplete), ("Metrics", Metrics)])
def test_an_object_bomb_is_refused_within_its_kinds_bounds_without_being_unpacked(kind, model):
    """Four million empty maps (4 MB) under a valid header: refused by the kind's bounds (a
    State may hold a few thousand maps and arrays, a RoundComplete one) after the first few,
    never built: the decode allocates next to nothing."""
    import tracemalloc

    payload = bomb(kind, depth=2, width=2048, round=1)
    assert len(payload) > 4_000_000
    tracemalloc.start()
    with pytest.raises(ProtocolError) as err:
        decode(payload, model, run=RUN, sender=2)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert err.value.reason in ("malformed", "oversized")
    assert peak < 2_000_000, f"{peak} bytes allocated to refuse it"


def test_a_goal_needs_a_path_of_points_unless_it_is_done_and_a_bounded_one():
    path = np.zeros((MAX_GOAL_PATH + 1, 2), np.float32)
    for bad, why in [({}, "needs a path"), ({"path": Tensor.of(np.zeros((0, 2), np.float32))}, "needs a path"),
                     ({"path": Tensor.of(np.zeros((3, 3), np.float32))}, "shape"),
                     ({"path": Tensor.of(path)}, "at most"), ({"path": Tensor.of(path[:2]), "leg": 0}, "leg")]:
        fields = {"run": RUN, "sender": 1, "leg": 1, "round": 10, **bad}
        with pytest.raises(ValueError, match=why):
            Goal(**fields)


def test_a_payload_whose_header_does_not_come_first_is_refused_before_its_body():
    """The header (v, kind, run, sender) is read from a message's first bytes: a payload that
    puts anything before it is refused as malformed, whatever follows."""
    doc = {"params": [0] * 10, "v": 2, "kind": "RoundComplete", "run": RUN, "sender": 2, "round": 1}
    with pytest.raises(ProtocolError, match="header") as err:
        decode(msgpack.packb(doc), RoundComplete, run=RUN, sender=2)
    assert err.value.reason == "malformed"


def test_a_refusal_never_repeats_a_long_message_into_the_log():
    """A refusal's detail is bounded, whatever the payload held (a 1 MB run name, say)."""
    payload = msgpack.packb({"v": 2, "kind": "RoundComplete", "run": RUN, "sender": 2, "round": "x" * 1_000_000})
    with pytest.raises(ProtocolError) as err:
        decode(payload, RoundComplete, run=RUN, sender=2)
    assert len(str(err.value)) < 300
