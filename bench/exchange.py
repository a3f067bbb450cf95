"""Algorithm 1's State exchange through the project's Bus and codec against raw Zenoh.

    python bench/exchange.py [--trips 200] [--sizes dinno,paper]

Two real processes on loopback (Zenoh peers, TCP, no TLS for both paths so that only the
project's own layers differ). The bench process is learner 0; a second process, started
with ``--role echo`` afresh for each size, is learner 1; both use the learner's own
:class:`ZenohTransport` for that size. For each State size (DiNNO's FourierNet, 25,601 values,
102 kB; the paper's BNN with mu and rho, 527,361 values, 2.1 MB):

- project: learner 0 sends its State with :class:`ZenohTransport` as a learner does (the
  node has flattened its parameters into the transport's ``new_state`` frame, so sending
  stamps the round and puts the frame); learner 1 receives it as Algorithm 1 does (decode,
  validate, shape check, an ``Envelope`` with a read-only view of the vector, handed to the
  exchange's thread) and answers with its own State the same way;
- raw: the same bytes with a bare ``session.put``; a subscriber's callback takes them out of
  Zenoh (``payload.to_bytes()``) and hands them to the application's own thread through the
  same kind of queue as the project's transport (Algorithm 1 runs on its own thread), which
  puts them back. So both paths have the same threads, and the difference is the project's
  Bus, codec, validation and transport.

One-way time is half the median round trip (the two paths' trips interleaved in blocks). Serialisation is the encode (stamp the frame) +
decode (validate, finiteness included) time of one State, measured in the bench process, as a
share of the project's one-way time; the JSON also gives ``encode_copy_s``, the encode of a
vector that is not in a frame (``encode_state``, one copy).
"""

from __future__ import annotations

import argparse
import json
import queue
import socket
import statistics
import subprocess
import sys
import threading
import time

import numpy as np
import torch
import zenoh

from swarmmap.services.learner.codec import StateCodec
from swarmmap.services.learner.zenoh_transport import ZenohTransport
from swarmmap.shared.bus import Bus
from swarmmap.shared.config import ZenohSettings
from swarmmap.shared.models import param_count
from swarmmap.shared.networks import build_model
from swarmmap.shared.protocol import Keys, State, StateFrame, decode, encode_state

RUN = "bench-exchange"
SIZES = {
    "dinno": ("DiNNO FourierNet", [2, 256, 64, 64, 64, 1], "fourier"),
    "paper": ("paper BNN", [2, 256, 256, 256, 256, 256, 1], "bnn"),
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def settings(listen: str | None, connect: str | None) -> ZenohSettings:
    return ZenohSettings(mode="peer", listen=[listen] if listen else ["tcp/127.0.0.1:0"],
                         connect=[connect] if connect else [], multicast_scouting=False, insecure=True)


def values(size: str) -> int:
    _, shape, kind = SIZES[size]
    return param_count(build_model(shape, 5.0, (0.0, 0.0, 1.0, 1.0), 0, kind))


def echo(endpoint: str, size: str) -> None:
    """Learner 1: send back every State (through the learner's own transport) and every raw payload."""
    bus = Bus.open(settings(None, endpoint), Keys("swarmmap", RUN), "learner", 1)
    raw_back = bus.session.declare_publisher("bench/raw/back", congestion_control=zenoh.CongestionControl.BLOCK)
    raw_out: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    bus.session.declare_subscriber("bench/raw/out", lambda s: raw_out.put(s.payload.to_bytes()))

    def raw_echo() -> None:
        while True:
            raw_back.put(raw_out.get())

    threading.Thread(target=raw_echo, daemon=True).start()
    n = values(size)
    transport = StateCodec(ZenohTransport(bus, 1, {0}, n), 1)  # as a learner's links are, uncompressed
    own = transport.new_state(n)  # this learner's State, as its node writes it
    own[:] = np.random.default_rng(2).standard_normal(n)
    bus.announce()
    print("ready", flush=True)
    while True:  # until the bench terminates this process
        env = transport.receive(1.0)
        if env is not None:
            transport.send_state(env.round, own)


def median_trips(paths: dict[str, tuple], trips: int, blocks: int = 10) -> dict[str, float]:
    """Median round trip of each path ``name: (send, receive)``, in interleaved blocks of
    trips, so that both paths see the same machine (2 shared cores drift)."""
    times: dict[str, list[float]] = {name: [] for name in paths}
    for block in range(blocks):
        for name, (send, receive) in paths.items():
            for r in range(trips // blocks + 2):
                t = time.perf_counter()
                send(r)
                receive()
                if r >= 2:  # warm-up trips
                    times[name].append(time.perf_counter() - t)
    return {name: statistics.median(ts) for name, ts in times.items()}


def serialisation(n: int, reps: int = 101) -> tuple[float, float, float]:
    """Seconds to encode one State as the transport sends a learner's (stamp its frame), to
    decode it into the vector Algorithm 1 gets (validated, a read-only view), and to encode a
    vector that is not in a frame (one copy)."""
    params = np.random.default_rng(0).standard_normal(n).astype(np.float32)
    vector = StateFrame.new(RUN, 0, n)
    vector[:] = params
    payload = bytes(StateFrame.of(vector).stamp(1))
    return (timed(lambda: StateFrame.of(vector).stamp(1), reps),
            timed(lambda: decode(payload, State, run=RUN, sender=0).params.numpy(), reps),
            timed(lambda: encode_state(RUN, 0, 1, params), reps))


def timed(call, reps: int) -> float:
    """Median seconds of one call (a median, like the trips': one preempted call is no figure)."""
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def measure(size: str, trips: int) -> dict:
    """One size, between this process and a fresh echo process (each with the transport a
    learner of that size has); prints the headline and returns the figures."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = Bus.open(settings(endpoint, None), Keys("swarmmap", RUN), "learner", 0)
    peer = subprocess.Popen([sys.executable, __file__, "--role", "echo", "--endpoint", endpoint, "--sizes", size],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert peer.stdout.readline().strip() == "ready", "the echo process did not start"
        deadline = time.monotonic() + 20
        while ("learner", "1") not in bus.alive("learner"):
            if time.monotonic() > deadline:
                raise SystemExit("the echo process never joined")
            time.sleep(0.1)
        raw_in: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        bus.session.declare_subscriber("bench/raw/back", lambda s: raw_in.put(s.payload.to_bytes()))
        raw_out = bus.session.declare_publisher("bench/raw/out", congestion_control=zenoh.CongestionControl.BLOCK)
        n = values(size)
        transport = StateCodec(ZenohTransport(bus, 0, {1}, n), 0)
        params = transport.new_state(n)  # this learner's State, as its node writes it
        params[:] = np.random.default_rng(1).standard_normal(n)
        payload = encode_state(RUN, 0, 1, params)

        def receive_state() -> None:
            if transport.receive(10.0) is None:
                raise SystemExit("a State was lost")

        trip = median_trips({"project": (lambda r: transport.send_state(r, params), receive_state),
                             "raw": (lambda r: raw_out.put(payload), lambda: raw_in.get(timeout=10))}, trips)
        project, raw = trip["project"] / 2, trip["raw"] / 2
    finally:
        peer.terminate()
        peer.wait(10)
        bus.close()
    enc, dec, enc_copy = serialisation(n)
    print(f"State exchange, {SIZES[size][0]} size {len(payload) / 1e6:.2f} MB: {project * 1e3:.2f} ms one-way, "
          f"{project / raw:.2f}x raw Zenoh ({raw * 1e3:.2f} ms), serialisation {100 * (enc + dec) / project:.0f}% "
          f"(encode {enc * 1e3:.2f} ms, decode {dec * 1e3:.2f} ms)", flush=True)
    return {"bytes": len(payload), "project_s": project, "raw_s": raw, "encode_s": enc, "decode_s": dec,
            "encode_copy_s": enc_copy}


def main() -> None:
    torch.set_num_threads(1)  # as a learner runs (learner.torch_threads)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trips", type=int, default=200)
    ap.add_argument("--sizes", default="dinno,paper")
    ap.add_argument("--role", default="bench", choices=["bench", "echo"])
    ap.add_argument("--endpoint", default=None)
    args = ap.parse_args()
    sizes = args.sizes.split(",")
    if args.role == "echo":
        echo(args.endpoint, sizes[0])
        return
    print(json.dumps({size: measure(size, args.trips) for size in sizes}))


if __name__ == "__main__":
    main()
