"""``swarmmap status``: the live services of a run (liveliness tokens) and their message rates.

Run-book: ``swarmmap status --config RUN_DIR/config.yaml`` (or ``--run-id ID`` with the Zenoh
options that reach the run). It lists every token under ``alive/``, listens to the run's keys
for ``--window`` seconds and prints messages and bytes per second of what each service publishes.
"""

from __future__ import annotations

import collections
import threading
import time

import zenoh

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig
from swarmmap.shared.protocol import Keys


def publisher_of(keys: Keys, key: str) -> tuple[str, str, str] | None:
    """(service, id, topic) of the service that publishes ``key``."""
    tail = key[len(keys.root) + 1 :].split("/")
    if len(tail) == 3 and tail[0] == "robots":
        return ("world", "0", "scan") if tail[2] == "scan" else ("lidar", tail[1], tail[2])
    if len(tail) == 3 and tail[0] == "learners":
        return "learner", tail[1], tail[2]
    return None


def collect(cfg: RunConfig, window: float) -> tuple[list[tuple[str, str]], dict[tuple[str, str], dict[str, list[float]]]]:
    """Live (service, id) pairs and, per pair, per topic [messages, bytes] seen in ``window`` s."""
    keys = Keys(cfg.key_prefix, cfg.run_id)
    counts: dict[tuple[str, str], dict[str, list[float]]] = collections.defaultdict(
        lambda: collections.defaultdict(lambda: [0, 0]))
    lock = threading.Lock()
    with Bus.open(cfg.zenoh, keys, "status", 0) as bus:

        def on_sample(sample: zenoh.Sample) -> None:
            who = publisher_of(keys, str(sample.key_expr))
            if who is not None:
                with lock:
                    c = counts[who[:2]][who[2]]
                    c[0] += 1
                    c[1] += len(sample.payload.to_bytes())

        sub = bus.session.declare_subscriber(keys.everything(), on_sample)
        time.sleep(window)
        sub.undeclare()
        alive = sorted(bus.alive(), key=lambda p: (p[0], int(p[1]) if p[1].isdigit() else 0))
    return alive, counts


def report(cfg: RunConfig, window: float) -> str:
    """The status table as text."""
    alive, counts = collect(cfg, window)
    lines = [f"run {cfg.run_id}: {len(alive)} service(s) alive (rates over {window:.1f} s)"]
    for service, ident in alive:
        if service in ("status", "exchange", "up"):  # the launcher and learners' exchange readiness
            continue
        rates = ", ".join(f"{topic} {n / window:.1f} msg/s {b / window / 1024:.1f} KiB/s"
                          for topic, (n, b) in sorted(counts.get((service, ident), {}).items()))
        lines.append(f"  {service:<8} {ident:>3}  {rates or 'idle'}")
    return "\n".join(lines)
