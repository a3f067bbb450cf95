"""Robot ids claimed at start, for per-robot services that all look alike (compose's replicas
of one lidar service and one learner service).

With ``SWARMMAP_ROBOT_CLAIMS=FOLDER`` in its environment (compose: a volume shared by the
run's containers), a lidar streamer or learner started without ``--robot`` (and outside SLURM)
takes the lowest robot id that no other holder has taken for its service. The claims are
``FOLDER/<service>.json`` (holder -> robot id), read and written under an exclusive ``flock``,
so replicas that start at once get distinct ids. The holder is the host name, which in a
container is the container's id: a container that restarts gets its own id back, and one more
than the run has robots is refused. Outside containers, processes that share a host name share
a claim: give them ``--robot`` instead.
"""

from __future__ import annotations

import fcntl
import json
import logging
import socket
from pathlib import Path

from swarmmap.shared.run.atomic import atomic_write_text

CLAIMS_ENV = "SWARMMAP_ROBOT_CLAIMS"

log = logging.getLogger("claim")


class ClaimError(Exception):
    """No robot id is left for this holder."""


def claim_robot(folder: Path, service: str, robots: int, holder: str | None = None) -> int:
    """The robot id ``holder`` (default: this host's name) holds for ``service``, claimed now
    if it holds none: the lowest of ``0..robots-1`` that nobody holds."""
    holder = holder or socket.gethostname()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{service}.json"
    with open(folder / f".{service}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or the process dies
        claims: dict[str, int] = json.loads(path.read_text()) if path.exists() else {}
        robot = claims.get(holder)
        if robot is None or not 0 <= robot < robots:
            free = sorted(set(range(robots)) - set(claims.values()))
            if not free:
                raise ClaimError(f"all {robots} robot ids of {service} are held ({path}: {json.dumps(claims)}); "
                                 f"more {service} containers than robots? (SWARMMAP_ROBOTS={robots})")
            robot = claims[holder] = free[0]
            atomic_write_text(path, json.dumps(claims, indent=1) + "\n")
    log.info("%s %s serves robot %d (claims in %s)", service, holder, robot, path)
    return robot


def claimed_robot(folder: str, field: str, robots: int) -> int:
    """The robot of the service whose robot field is ``field`` (``learner.robot``), claimed in
    ``folder``; a :class:`ClaimError` naming the field when none is left."""
    try:
        return claim_robot(Path(folder), field.split(".")[0], robots)
    except (ClaimError, OSError, ValueError) as exc:  # ValueError: a claims file that is not JSON
        raise ClaimError(f"config error:\n  {field}: no robot id to claim in {folder} ({CLAIMS_ENV}): {exc}") from None


def forget_claims(folder: Path) -> None:
    """Drop every claim in ``folder`` (a new ``up``: its containers claim afresh)."""
    for path in folder.glob("*.json"):
        path.unlink()
