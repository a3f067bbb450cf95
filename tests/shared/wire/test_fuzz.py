"""Property-based fuzzing of every wire decoder: whatever bytes arrive, ``decode`` returns a valid
message of the kind asked for or refuses it with a ProtocolError, within 256 MiB more memory;
never another exception. Three sources of input: random bytes, valid payloads mutated (bytes
flipped, cut, repeated), and msgpack documents with a valid header and random bodies."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarmmap.shared.wire.codec import decode, encode, encode_state
from swarmmap.shared.wire.compression import compressor
from swarmmap.shared.wire.protocol import (
    MESSAGE_TYPES,
    Goal,
    Metrics,
    ProtocolError,
    RoundComplete,
    RunDone,
    Samples,
    Scan,
    Tensor,
    WorldMap,
)
from tests.fuzzing import mutation_of

RUN = "run-1"
KINDS = sorted(MESSAGE_TYPES)
FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def valid_messages() -> list[bytes]:
    """A valid payload of every kind (a State plain and compressed)."""
    v = np.linspace(-1, 1, 64, dtype=np.float32)
    quant = compressor("quant", bits=4)
    quant.body(v)  # (a key frame first: the next is a quantised difference)
    return [
        encode_state(RUN, 2, 7, v),
        encode(quant.body(v * 0.9).state(RUN, 2, 7)),
        encode(RoundComplete(run=RUN, sender=2, round=3)),
        encode(Metrics(run=RUN, sender=2, round=5, wall_time_s=1.5, val_bce=0.3, consensus_error=0.01, bytes_sent=10,
                       bytes_received=20, pid=42, final=True)),
        encode(Scan(run=RUN, sender=2, seq=1, t=0.5, pose=[1.0, 2.0, 0.1], max_range=3.5,
                    angles=Tensor.of(np.zeros(4, np.float32)), ranges=Tensor.of(np.ones(4, np.float32)),
                    hit=Tensor.of(np.ones(4, np.uint8)))),
        encode(Samples(run=RUN, sender=2, seq=1, t=0.5, position=[0.0, 0.0], points=Tensor.of(np.zeros((3, 2), np.float32)),
                       labels=Tensor.of(np.array([0, 1, 0], np.float32)), last=True)),
        encode(WorldMap(run=RUN, sender=2, resolution=0.1, origin=[0.0, 0.0], grid=Tensor.of(np.eye(3, dtype=np.uint8)),
                        val_points=Tensor.of(np.zeros((2, 2), np.float32)), val_labels=Tensor.of(np.zeros(2, np.float32)),
                        robots=3)),
        encode(RunDone(run=RUN, sender=2, ok=True, reason="all finished", finished=[0, 1, 2])),
        encode(Goal(run=RUN, sender=2, leg=3, round=30, x=1.0, y=2.0, path=Tensor.of(np.array([[0, 0], [1, 2]], np.float32)),
                    reason="std 3.1 over 2.2 m")),
    ]


VALID = valid_messages()
TRIED: dict[str, int] = {}


def judged(payload: bytes, kind: str, source: str) -> None:
    """``payload`` decoded as ``kind``: a message of that kind, or a ProtocolError; nothing else."""
    TRIED[source] = TRIED.get(source, 0) + 1
    try:
        msg = decode(payload, MESSAGE_TYPES[kind], run=RUN, sender=2)
    except ProtocolError as err:
        assert len(str(err)) < 300, "a refusal repeats the payload into the log"
        return
    assert type(msg) is MESSAGE_TYPES[kind] and msg.run == RUN and msg.sender == 2


@pytest.fixture(autouse=True, scope="module")
def _report_inputs():
    yield
    print(f"\nwire decoders fuzzed: {', '.join(f'{n} {s}' for s, n in sorted(TRIED.items()))} inputs")


@FUZZ
@given(payload=st.binary(max_size=2048), kind=st.sampled_from(KINDS))
def test_random_bytes_are_refused_or_decoded(memory_limit, payload, kind):
    memory_limit(256)
    judged(payload, kind, "random")


@FUZZ
@given(payload=st.sampled_from(VALID).flatmap(mutation_of), kind=st.sampled_from(KINDS))
def test_mutated_payloads_are_refused_or_decoded(memory_limit, payload, kind):
    memory_limit(256)
    judged(payload, kind, "mutated")


leaves = st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=20) | st.binary(max_size=64)
bodies = st.recursive(leaves, lambda inner: st.lists(inner, max_size=8) | st.dictionaries(st.text(max_size=8), inner, max_size=8),
                      max_leaves=64)


@FUZZ
@given(kind=st.sampled_from(KINDS), body=st.dictionaries(st.sampled_from(
    ["round", "params", "seq", "t", "pose", "points", "labels", "final", "encoding", "blocks", "grid", "ok", "reason", "x"]),
    bodies, max_size=10))
def test_documents_with_a_valid_header_and_any_body_are_refused_or_decoded(memory_limit, kind, body):
    memory_limit(256)
    doc = {"v": 2 if kind == "State" else 1, "kind": kind, "run": RUN, "sender": 2, **body}
    judged(msgpack.packb(doc, use_bin_type=True), kind, "documents")
