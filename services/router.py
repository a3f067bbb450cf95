"""The router service: a Zenoh session in router mode, for discovery across hosts and containers.

Run-book: ``swarmmap router --zenoh-listen tcp/0.0.0.0:7447``; other services then connect
with ``--zenoh-connect tcp/<host>:7447``. Data still flows peer to peer where peers can reach
each other; the router relays where they cannot.
"""

from __future__ import annotations

import logging
import threading

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig
from swarmmap.shared.protocol import Keys

log = logging.getLogger("router")


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Serve as a router until stopped."""
    settings = cfg.zenoh.model_copy(update={"mode": "router"})
    with Bus.open(settings, Keys(cfg.key_prefix, cfg.run_id), "router", 0) as bus:
        bus.announce()
        log.info("router up, listening on %s", ", ".join(settings.listen) or "Zenoh's default endpoints")
        stop.wait()
    return 0
