"""The router service: a Zenoh session in router mode, for discovery across hosts and containers.

Run-book: ``swarmmap router --zenoh-listen tcp/0.0.0.0:7447``; other services then connect
with ``--zenoh-connect tcp/<host>:7447``. Data still flows peer to peer where peers can reach
each other; the router relays where they cannot. It exits when the run is over (``run/done``)
and every other service of the run has left, or when stopped.
"""

from __future__ import annotations

import logging
import threading
import time

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig
from swarmmap.shared.protocol import Keys

log = logging.getLogger("router")


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Serve as a router until stopped."""
    settings = cfg.zenoh.model_copy(update={"mode": "router"})
    with Bus.open(settings, Keys(cfg.key_prefix, cfg.run_id), "router", 0) as bus:
        bus.end_with_run(stop)
        bus.announce()
        log.info("router up, listening on %s", ", ".join(settings.listen) or "Zenoh's default endpoints")
        stop.wait()
        if bus.run_done is not None:  # the run is over: stay while the others leave through us
            deadline = time.monotonic() + cfg.leave_s()
            while time.monotonic() < deadline and {s for s, _ in bus.alive()} - {"router", "up", "status"}:
                time.sleep(0.5)
    return 0
