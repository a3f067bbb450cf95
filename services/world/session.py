"""The world's Zenoh session, the same for a simulated world and a world of real logs: the map
served on ``world/map``, a scan publisher per robot, and the wait for the services that must be
alive before the robots drive."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.protocol import Keys

log = logging.getLogger("world")


def wait_for_consumers(cfg: RunConfig, bus: Bus, stop: threading.Event) -> bool:
    """Wait (up to ``world.wait_for_consumers_s``) for the services of ``world.wait_for``; False
    when told to stop meanwhile."""
    w = cfg.world
    deadline = time.monotonic() + w.wait_for_consumers_s
    # exploring, each learner listens to its team's goals and scans before the first scan (its "explore" token)
    for service in [*w.wait_for, *(["explore"] if cfg.explore.active and "learner" in w.wait_for else [])]:
        wanted = {str(i) for i in range(cfg.robots)} if service in ("lidar", "learner", "explore") else {"0"}
        missing = bus.wait_alive(service, wanted, max(0.0, deadline - time.monotonic()), stop)
        if stop.is_set():
            return False
        if missing:
            log.warning("driving without %s %s (not alive after %.0f s)", service, sorted(missing), w.wait_for_consumers_s)
    return True


def wait_for_subscribers(pubs: list, stop: threading.Event, timeout: float = 10.0) -> None:
    """Wait (up to ``timeout``) until every robot's scan publisher knows a subscriber (what it sends
    before is dropped); warn naming the robots that have none."""
    if waiting := Bus.wait_matched(pubs, timeout, stop):
        log.warning("driving although no subscriber of %s is known yet (their first scans may be lost)",
                    ", ".join(p.key for p in waiting))



@contextmanager
def serving(cfg: RunConfig, reply: Callable[[str], bytes], stop: threading.Event,
            listen: Callable[[Bus], None] | None = None) -> Iterator[list | None]:
    """The world's session: ``reply(parameters)`` (an encoded WorldMap) served on ``world/map``,
    a scan publisher per robot, ``listen(bus)``'s subscriptions, announced; yields the publishers
    once the consumers are alive, or None when the world must not drive (``world.drive`` off:
    after the run is over; or stopped while waiting)."""
    keys = Keys(cfg.key_prefix, cfg.run_id)
    with Bus.open(cfg.zenoh, keys, "world", 0) as bus:
        bus.end_with_run(stop)
        bus.serve(keys.world_map(), reply)
        pubs = [bus.publisher(keys.scan(i)) for i in range(cfg.robots)]
        if listen is not None:
            listen(bus)
        bus.announce()
        if not cfg.world.drive:
            log.info("serving the map only (world.drive is off)")
            stop.wait()
            yield None
        else:
            ready = wait_for_consumers(cfg, bus, stop)
            if ready and "lidar" in cfg.world.wait_for:
                wait_for_subscribers(pubs, stop)
            yield pubs if ready and not stop.is_set() else None
