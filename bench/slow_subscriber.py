"""Can a slow subscriber throttle a publisher? A 2 MB State publisher against a subscriber whose
callback sleeps 0.5 s, on a secure run's router (mutual TLS, the run's access policy).

    python bench/slow_subscriber.py [--seconds 6] [--cases baseline,before,after,drop,stuck,status]

Every party is its own process: the router, learner 0 publishing States of 527,361 values (the
paper's BNN, 2.1 MB) as fast as it can for ``--seconds``, learner 1 (a neighbour: it must get
every State) and, except in ``baseline``, a slow subscriber. Cases:

- ``baseline``: no slow subscriber;
- ``before``: the observer's credentials, its callback (0.5 s) on Zenoh's receiving thread, the
  publisher's congestion control BLOCK (every data publisher of the project);
- ``after``: the same callback behind the Bus's ring (``Bus.subscribe(..., newest=4)``, what the
  observer and ``up`` use);
- ``drop``: the callback on Zenoh's thread, the publisher's congestion control DROP;
- ``fast``: the observer with a quick callback (the same fan-out as the slow cases, for reference);
- ``stuck``: a callback that never returns (a process that stops reading), BLOCK; the router
  closes a link it could not send on for 2 s, the publisher its own after 60 s (the Bus's
  settings, ``ROUTER_CLOSES_STUCK_S``);
- ``stuck-zenoh-default``: the same with Zenoh's default, 5 s, for the router and the publisher;
- ``status``: ``status-0`` subscribing to every key with the 0.5 s callback on Zenoh's thread,
  as the issue measured it; the access policy lets it read no State.

Prints one JSON line per case: States sent by the publisher, States received by learner 1
and by the slow subscriber, messages per second sent.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from swarmmap.shared.run.config import ZenohSettings
from swarmmap.shared.run.runtime import shutdown_event
from swarmmap.shared.wire import bus as bus_module
from swarmmap.shared.wire.bus import ROUTER_CLOSES_STUCK_S, Bus
from swarmmap.shared.wire.codec import encode_state
from swarmmap.shared.wire.protocol import Keys, State
from swarmmap.shared.wire.secrets import access_policy, router_names, write_credentials
from swarmmap.shared.wire.services import identities

RUN = "bench-slow"
VALUES = 527_361  # the paper's BNN: mu and rho of 263,680 weights, and the round
SLOW_S = 0.5


def settings(folder: Path, endpoint: str, **extra) -> ZenohSettings:
    return ZenohSettings(connect=[endpoint], multicast_scouting=False, secrets=folder, connect_timeout_s=20, **extra)


def role_router(folder: Path, endpoint: str, stop: threading.Event) -> dict:
    keys = Keys("swarmmap", RUN)
    router = ZenohSettings(mode="router", listen=[endpoint], multicast_scouting=False, secrets=folder)
    with Bus.open(router, keys, "router", 0, policy=access_policy(keys, 2, neighbours={0: {1}, 1: {0}})):
        stop.wait()
    return {}


def role_publisher(folder: Path, endpoint: str, stop: threading.Event, seconds: float, congestion: str, wait_for: str) -> dict:
    keys = Keys("swarmmap", RUN)
    with Bus.open(settings(folder, endpoint), keys, "learner", 0) as bus:
        for service, ident in (s.split("-") for s in wait_for.split(",") if s):
            if bus.wait_alive(service, {ident}, 60, stop):
                raise SystemExit(f"{service}-{ident} never came alive")
        time.sleep(1.0)  # the subscriptions reach the router after the tokens
        cc = zenoh.CongestionControl.DROP if congestion == "drop" else zenoh.CongestionControl.BLOCK
        pub = bus.session.declare_publisher(keys.state(0), congestion_control=cc, reliability=zenoh.Reliability.RELIABLE)
        payload = encode_state(RUN, 0, 0, np.zeros(VALUES, np.float32))
        sent, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds and not stop.is_set():
            pub.put(payload)
            sent += 1
        wall = time.monotonic() - t0
        pub.undeclare()
    return {"sent": sent, "wall_s": round(wall, 2)}


def role_subscriber(folder: Path, endpoint: str, stop: threading.Event, who: str, how: str, out: Path) -> dict:
    """learner-1 (every State, a quick callback), or a slow one: ``zenoh`` (0.5 s on Zenoh's
    thread), ``ring`` (0.5 s behind the Bus's ring), ``stuck`` (never returns), ``status``."""
    keys = Keys("swarmmap", RUN)
    got = [0]

    def on_state(msg: State) -> None:
        got[0] += 1
        if how in ("zenoh", "ring"):
            time.sleep(SLOW_S)
        elif how == "stuck":
            stop.wait()

    service, ident = who.rsplit("-", 1)
    with Bus.open(settings(folder, endpoint), keys, service, ident) as bus:
        if how == "status":
            def on_sample(sample: zenoh.Sample) -> None:
                got[0] += "/state" in str(sample.key_expr)
                time.sleep(SLOW_S)
            bus.session.declare_subscriber(keys.everything(), on_sample)
        else:
            bus.subscribe(keys.state(0), State, on_state, newest=4 if how == "ring" else 0)
        bus.announce()
        while not stop.wait(0.5):  # the count so far, should this process have to be killed
            out.write_text(json.dumps({"received": got[0]}))
        out.write_text(json.dumps({"received": got[0]}))
    return {"received": got[0]}


CASES = {  # case: (slow subscriber identity, its kind, the publisher's congestion control, the router's close time)
    "baseline": (None, None, "block", None),
    "fast": ("observer-0", "fast", "block", None),
    "before": ("observer-0", "zenoh", "block", None),
    "after": ("observer-0", "ring", "block", None),
    "drop": ("observer-0", "zenoh", "drop", None),
    "stuck": ("observer-0", "stuck", "block", None),
    "stuck-zenoh-default": ("observer-0", "stuck", "block", 5.0),  # the router's and the publisher's
    "status": ("status-0", "status", "block", None),
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(role: str, folder: Path, endpoint: str, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, "--role", role, "--folder", str(folder), "--endpoint", endpoint,
                             "--out", str(out), *extra])


def settle(out: Path, quiet_s: float = 3.0, timeout: float = 60.0) -> None:
    """Wait until the count in ``out`` has not changed for ``quiet_s`` (at most ``timeout``)."""
    last, since, deadline = None, time.monotonic(), time.monotonic() + timeout
    while time.monotonic() < deadline:
        now = out.read_text() if out.exists() else None
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since > quiet_s:
            return
        time.sleep(0.2)


def run_case(case: str, folder: Path, seconds: float) -> dict:
    slow, how, congestion, close_after_s = CASES[case]
    endpoint = f"tls/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp())
    close = ["--close-after-s", str(close_after_s)] if close_after_s else []
    procs = [start("router", folder, endpoint, tmp / "router.json", *close)]
    procs.append(start("sub", folder, endpoint, tmp / "fast.json", "--who", "learner-1", "--how", "fast"))
    wait_for = "learner-1"
    if slow is not None:
        procs.append(start("sub", folder, endpoint, tmp / "slow.json", "--who", slow, "--how", how))
        wait_for += "," + slow
    publisher = start("pub", folder, endpoint, tmp / "pub.json", "--seconds", str(seconds), "--congestion", congestion,
                      "--wait-for", wait_for, *close)
    try:
        publisher.wait(timeout=seconds + 120)
        settle(tmp / "fast.json")  # what is on its way arrives
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    pub = json.loads((tmp / "pub.json").read_text())
    fast = json.loads((tmp / "fast.json").read_text())
    slow_got = json.loads((tmp / "slow.json").read_text())["received"] if slow else None
    return {"case": case, "slow": slow and f"{slow} ({how})", "congestion": congestion,
            "router_close_s": close_after_s or ROUTER_CLOSES_STUCK_S, "sent": pub["sent"],
            "per_s": round(pub["sent"] / pub["wall_s"], 1), "learner_1_received": fast["received"], "slow_received": slow_got}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--role")
    parser.add_argument("--folder", type=Path)
    parser.add_argument("--endpoint")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--who")
    parser.add_argument("--how")
    parser.add_argument("--congestion", default="block")
    parser.add_argument("--wait-for", default="")
    parser.add_argument("--close-after-s", type=float)
    args = parser.parse_args()
    if args.role:
        stop = shutdown_event()
        if args.close_after_s is not None:  # how long this session waits on a link it cannot send on
            bus_module.ROUTER_CLOSES_STUCK_S = bus_module.CLIENT_CLOSES_STUCK_S = args.close_after_s
        if args.role == "router":
            result = role_router(args.folder, args.endpoint, stop)
        elif args.role == "pub":
            result = role_publisher(args.folder, args.endpoint, stop, args.seconds, args.congestion, args.wait_for)
        else:
            result = role_subscriber(args.folder, args.endpoint, stop, args.who, args.how, args.out)
        args.out.write_text(json.dumps(result))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "secrets"
        write_credentials(folder, RUN, identities(2), router_names(["tls/127.0.0.1:1"]))
        for case in args.cases.split(","):
            print(json.dumps(run_case(case, folder, args.seconds)), flush=True)


if __name__ == "__main__":
    main()
