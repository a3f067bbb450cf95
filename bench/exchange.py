"""Algorithm 1's State exchange through the project's Bus and codec against raw Zenoh.

    python bench/exchange.py [--trips 200] [--sizes dinno,paper] [--secure]

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

``--secure``: the same two learners as a secure run has them, each a client of its run's
router over mutual TLS with credentials of its own (``shared/wire/secrets.py``), the router (a
process of its own) enforcing the run's access policy; the raw path is two bare sessions with
the same certificates through a second router with TLS and no access control. So both paths
cross TLS and a router, and the difference is the project's layers and the policy.

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
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch
import zenoh

from swarmmap.services.learner.codec import StateCodec
from swarmmap.services.learner.zenoh_transport import ZenohTransport
from swarmmap.shared.learning.models import param_count
from swarmmap.shared.learning.networks import build_model
from swarmmap.shared.run.config import ZenohSettings
from swarmmap.shared.wire.bus import Bus, zenoh_config
from swarmmap.shared.wire.codec import StateFrame, decode, encode_state
from swarmmap.shared.wire.protocol import Keys, State
from swarmmap.shared.wire.secrets import access_policy, write_credentials

RUN = "bench-exchange"
SIZES = {
    "dinno": ("DiNNO FourierNet", [2, 256, 64, 64, 64, 1], "fourier"),
    "paper": ("paper BNN", [2, 256, 256, 256, 256, 256, 1], "bnn"),
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def settings(listen: str | None, connect: str | None, secrets: Path | None = None) -> ZenohSettings:
    """Peers over plain TCP, or (``secrets``) a secure client of the router at ``connect``."""
    if secrets is not None:
        return ZenohSettings(mode="client", connect=[connect], secrets=secrets)
    return ZenohSettings(mode="peer", listen=[listen] if listen else ["tcp/127.0.0.1:0"],
                         connect=[connect] if connect else [], multicast_scouting=False, insecure=True)


def raw_session(endpoint: str, secrets: Path | None, who: str) -> zenoh.Session:
    """A bare Zenoh session for the raw path: the same transport as the project's (``secrets``: a
    TLS client of the raw router, with ``who``'s certificate), none of its layers."""
    if secrets is None:
        return zenoh.open(zenoh_config(settings(None, endpoint), who))
    return zenoh.open(zenoh_config(settings(None, endpoint, secrets), who, RUN))


def router(endpoint: str, secrets: Path, policy: bool) -> None:
    """A router of the run over TLS: with the run's access policy (the project's path) or with
    none (the raw path); until the bench terminates this process."""
    conf = zenoh_config(ZenohSettings(mode="router", listen=[endpoint], secrets=secrets), "router-0", RUN,
                        access_policy(Keys("swarmmap", RUN), 2))
    if not policy:
        conf.insert_json5("access_control", json.dumps({"enabled": False}))
    session = zenoh.open(conf)
    print("ready", flush=True)
    threading.Event().wait()
    session.close()


def values(size: str) -> int:
    _, shape, kind = SIZES[size]
    return param_count(build_model(shape, 5.0, (0.0, 0.0, 1.0, 1.0), 0, kind))


def echo(endpoint: str, size: str, raw_endpoint: str | None, secrets: Path | None) -> None:
    """Learner 1: send back every State (through the learner's own transport) and every raw payload."""
    bus = Bus.open(settings(None, endpoint, secrets), Keys("swarmmap", RUN), "learner", 1)
    raw = bus.session if secrets is None else raw_session(raw_endpoint, secrets, "learner-1")
    raw_back = raw.declare_publisher("bench/raw/back", congestion_control=zenoh.CongestionControl.BLOCK)
    raw_out: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    raw.declare_subscriber("bench/raw/out", lambda s: raw_out.put(s.payload.to_bytes()))

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


def start(*args: str) -> subprocess.Popen:
    """This script in another role, once it says it is ready."""
    proc = subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready", f"the {args[1]} process did not start"
    return proc


def measure(size: str, trips: int, secure: bool = False) -> dict:
    """One size, between this process and a fresh echo process (each with the transport a
    learner of that size has; ``secure``: each a TLS client of a router of its own path);
    prints the headline and returns the figures."""
    helpers, secrets, raw = [], None, None
    if secure:
        secrets = Path(tempfile.mkdtemp(prefix="bench-exchange-")) / "secrets"
        write_credentials(secrets, RUN, ["router-0", "learner-0", "learner-1"], ["127.0.0.1", "localhost"])
        endpoint, raw_endpoint = (f"tls/127.0.0.1:{free_port()}" for _ in range(2))
        helpers += [start("--role", "router", "--endpoint", endpoint, "--secrets", str(secrets)),
                    start("--role", "raw-router", "--endpoint", raw_endpoint, "--secrets", str(secrets))]
        bus = Bus.open(settings(None, endpoint, secrets), Keys("swarmmap", RUN), "learner", 0)
        raw = raw_session(raw_endpoint, secrets, "learner-0")
        echo_args = ["--endpoint", endpoint, "--raw-endpoint", raw_endpoint, "--secrets", str(secrets)]
    else:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        bus = Bus.open(settings(endpoint, None), Keys("swarmmap", RUN), "learner", 0)
        raw, echo_args = bus.session, ["--endpoint", endpoint]
    try:
        helpers.append(start("--role", "echo", "--sizes", size, *echo_args))
        deadline = time.monotonic() + 20
        while ("learner", "1") not in bus.alive("learner"):
            if time.monotonic() > deadline:
                raise SystemExit("the echo process never joined")
            time.sleep(0.1)
        raw_in: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        raw.declare_subscriber("bench/raw/back", lambda s: raw_in.put(s.payload.to_bytes()))
        raw_out = raw.declare_publisher("bench/raw/out", congestion_control=zenoh.CongestionControl.BLOCK)
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
        project, raw_s = trip["project"] / 2, trip["raw"] / 2
    finally:
        for proc in helpers:
            proc.terminate()
            proc.wait(10)
        if raw is not bus.session:
            raw.close()
        bus.close()
    enc, dec, enc_copy = serialisation(n)
    path, ref = (", secure path (TLS clients of a router with the access policy)", "raw Zenoh with TLS through a router") \
        if secure else ("", "raw Zenoh")
    print(f"State exchange{path}, {SIZES[size][0]} size {len(payload) / 1e6:.2f} MB: {project * 1e3:.2f} ms one-way, "
          f"{project / raw_s:.2f}x {ref} ({raw_s * 1e3:.2f} ms), serialisation {100 * (enc + dec) / project:.0f}% "
          f"(encode {enc * 1e3:.2f} ms, decode {dec * 1e3:.2f} ms)", flush=True)
    return {"bytes": len(payload), "secure": secure, "project_s": project, "raw_s": raw_s, "encode_s": enc, "decode_s": dec,
            "encode_copy_s": enc_copy}


def main() -> None:
    torch.set_num_threads(1)  # as a learner runs (learner.torch_threads)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trips", type=int, default=200)
    ap.add_argument("--sizes", default="dinno,paper")
    ap.add_argument("--secure", action="store_true", help="TLS clients of a router, as a secure run (the default) has them")
    ap.add_argument("--role", default="bench", choices=["bench", "echo", "router", "raw-router"])
    ap.add_argument("--endpoint", default=None)
    ap.add_argument("--raw-endpoint", default=None)
    ap.add_argument("--secrets", type=Path, default=None)
    args = ap.parse_args()
    sizes = args.sizes.split(",")
    if args.role == "echo":
        echo(args.endpoint, sizes[0], args.raw_endpoint, args.secrets)
        return
    if args.role in ("router", "raw-router"):
        router(args.endpoint, args.secrets, policy=args.role == "router")
        return
    print(json.dumps({size: measure(size, args.trips, args.secure) for size in sizes}))


if __name__ == "__main__":
    main()
