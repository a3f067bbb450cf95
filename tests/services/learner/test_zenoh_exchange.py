"""Real Zenoh sessions on free loopback ports: State exchange, refusal of bad payloads, and
Algorithm 1 between two OS processes giving the reference result."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Keys, ProtocolError, State, Tensor
from tests.conftest import wait_until

HERE = Path(__file__).parent


def three_params(msg: State) -> None:
    if msg.params.shape != [3]:
        raise ProtocolError("shape", f"expected 3 parameters, got {msg.params.shape}")


@contextlib.contextmanager
def learner_pair(zenoh_pair, run_id):
    """(keys, a, b, got): learner 0's bus ``a`` and learner 1's ``b``, which takes learner 0's
    States of three parameters into ``got``, once ``a`` sees ``b`` alive."""
    a_settings, b_settings = zenoh_pair
    keys = Keys("swarmmap", run_id)
    got: list[State] = []
    with Bus.open(a_settings, keys, "learner", 0) as a, Bus.open(b_settings, keys, "learner", 1) as b:
        b.subscribe(keys.state(0), State, got.append, check=three_params)
        b.announce()
        assert wait_until(lambda: ("learner", "1") in a.alive("learner"), 10)
        yield keys, a, b, got


@pytest.mark.integration
def test_two_sessions_exchange_state_and_drop_bad_payloads(zenoh_pair, run_id):
    with learner_pair(zenoh_pair, run_id) as (keys, a, b, got):
        pub = a.publisher(keys.state(0))
        raw = a.session.declare_publisher(keys.state(0))
        good = np.array([1.5, -2.0, 3.25], np.float32)
        raw.put(b"\x00garbage")
        raw.put(encode(State(run="other-run", sender=0, round=0, params=Tensor.of(good))))
        raw.put(encode(State(run=run_id, sender=5, round=0, params=Tensor.of(good))))  # speaks for robot 5
        raw.put(encode(State(run=run_id, sender=0, round=0, params=Tensor.of(np.zeros(4, np.float32)))))
        doc = State(run=run_id, sender=0, round=0, params=Tensor.of(good)).model_dump()
        doc["params"]["data"] = np.array([1, np.inf, 2], np.float32).tobytes()
        raw.put(msgpack.packb(doc))
        pub.put(State(run=run_id, sender=0, round=4, params=Tensor.of(good)))
        assert wait_until(lambda: len(got) == 1, 10)
        assert got[0].round == 4 and got[0].params.numpy().tolist() == good.tolist()
        assert wait_until(lambda: sum(b.dropped.values()) == 5, 5)
        assert dict(b.dropped) == {"malformed": 1, "wrong-run": 1, "unknown-sender": 1, "shape": 1, "non-finite": 1}
        assert a.sent.bytes_where(lambda k: k.endswith("/state")) > 0


@pytest.mark.integration
def test_a_key_that_floods_refused_payloads_is_muted_and_its_bombs_are_not_unpacked(zenoh_pair, run_id):
    """A member that sends object bombs (a valid header, then 65,536 empty maps) again and
    again: each is refused by its bounds, and after REFUSALS_TO_MUTE of them in a few seconds
    its key is muted: what it sends next, a valid State too, is dropped unread and counted."""
    from swarmmap.shared.wire.bus import REFUSALS_TO_MUTE

    with learner_pair(zenoh_pair, run_id) as (keys, a, b, got):
        pub = a.publisher(keys.state(0))
        assert wait_until(pub.matched, 10)  # (what a publisher sends before it knows its subscriber is lost)
        head = msgpack.packb({"v": 2, "kind": "State", "run": run_id, "sender": 0, "round": 0})
        bomb = b"\xde\x00\x06" + head[1:] + msgpack.packb("params") + b"\xdd" + (1 << 16).to_bytes(4, "big") + b"\x80" * (1 << 16)
        for _ in range(REFUSALS_TO_MUTE):
            pub.put_bytes(bomb)
        assert wait_until(lambda: b.dropped["malformed"] == REFUSALS_TO_MUTE, 30)
        pub.put(State(run=run_id, sender=0, round=1, params=Tensor.of(np.ones(3, np.float32))))
        assert wait_until(lambda: b.dropped["muted"] == 1, 30)
        assert got == [] and b.muted(keys.state(0))


@pytest.mark.integration
def test_algorithm1_between_two_processes_matches_reference(zenoh_pair, run_id, tmp_path):
    rounds = 8
    procs = []
    for node, settings in enumerate(zenoh_pair):
        procs.append(subprocess.Popen([sys.executable, str(HERE / "a1_node.py"), str(node), str(rounds), run_id,
                                       settings.model_dump_json(), str(tmp_path / f"{node}.npy")]))
    for p in procs:
        assert p.wait(timeout=90) == 0
    thetas = {i: np.full(4, float(i), np.float32) for i in (0, 1)}
    for k in range(rounds):
        thetas = {i: ((thetas[i] + thetas[1 - i]) / 2 + 0.01 * (k + 1) * (i + 1)).astype(np.float32) for i in (0, 1)}
    for i in (0, 1):
        np.testing.assert_array_equal(np.load(tmp_path / f"{i}.npy"), thetas[i])
