"""The router service: a Zenoh session in router mode, for discovery across hosts and containers.

Run-book: ``swarmmap router --zenoh-listen tcp/0.0.0.0:7447``; other services then connect
with ``--zenoh-connect tcp/<host>:7447``. With a router per host (``up.routers: per-host``,
shared/wire/mesh.py) each is started with ``--ident r<i>`` on robot ``i``'s host and
``--zenoh-connect`` naming the routers it links to; the routers relay for each other. In a secure run (the default) every endpoint is TLS
(``tcp/`` is served as ``tls/``, other protocols are refused; without ``--zenoh-listen`` it
listens on ``tls/[::]:7447``), every other service is its client, and it enforces the run's
access policy (:func:`run_policy`). It exits when the run is over (``run/done``) and every
other service of the run has left, or when stopped.
"""

from __future__ import annotations

import logging
import threading
import time

from swarmmap.shared.learning.graphs import GraphError, run_graph
from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.bus import LINKED_ROUTER_CLOSES_STUCK_S, Bus
from swarmmap.shared.wire.protocol import Keys
from swarmmap.shared.wire.secrets import access_policy

log = logging.getLogger("router")


def run_policy(cfg: RunConfig) -> dict:
    """The run's access policy (shared/wire/secrets.py): learners read their neighbours' exchange
    keys when the graph is known before the robots drive, every learner's otherwise."""
    spec = cfg.graph()
    neighbours = None
    if spec.kind != "disk" and not spec.dynamic:
        try:
            neighbours = run_graph(spec, cfg.robots, None)
        except GraphError:  # the learners refuse it themselves, naming it
            neighbours = None
    return access_policy(Keys(cfg.key_prefix, cfg.run_id), cfg.robots, inproc_learner=cfg.learner.transport == "inproc",
                         neighbours=neighbours, host_routers=cfg.router_per_host())


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Serve as a router until stopped."""
    linked = cfg.router_per_host() or bool(cfg.zenoh.connect)  # other routers on the far side of its links
    settings = cfg.zenoh.model_copy(update={"mode": "router", "stuck_s": cfg.zenoh.stuck_s or
                                            (LINKED_ROUTER_CLOSES_STUCK_S if linked else None)})
    policy = None if settings.insecure else run_policy(cfg)
    with Bus.open(settings, Keys(cfg.key_prefix, cfg.run_id), "router", cfg.router.ident, policy=policy) as bus:
        bus.end_with_run(stop)
        bus.announce()
        log.info("router-%s up, listening on %s%s", cfg.router.ident, ", ".join(settings.listen) or "Zenoh's default endpoints",
                 f"; linking to {', '.join(settings.connect)}" if settings.connect else "")
        stop.wait()
        if bus.run_done is not None:  # the run is over: stay while the others leave through us
            deadline = time.monotonic() + cfg.leave_s()
            while time.monotonic() < deadline and {s for s, _ in bus.alive()} - {"router", "up", "status"}:
                time.sleep(0.5)
    return 0
