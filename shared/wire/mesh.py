"""A run's hosts and the links between their routers: one router per host, no single point of failure.

A run with ``up.routers: per-host`` has a host per robot (``r0``, ``r1``, ...) and the base host
(``base``: the world, the recorder, the observer, ``up``). Each host runs a router; the
services of a host are clients of their own router only (as ROS 2's rmw_zenoh runs one router per
host), and the routers link to each other as ``up.router_links`` says:

- ``ring`` (the default): each host to the next, the last to the first: every host has two links,
  and the team stays connected when any one host or router is lost;
- ``full``: every host to every other;
- ``star``: every robot to the base only (one router carries everything: a single point of failure);
- a list of links, e.g. ``base-r0,r0-r1,r1-r2,r2-base``.

Each link is dialled by one side (the first named) and retried for ever; Zenoh's routers find
their routes over whatever links are up (link-state routing), so traffic between two robots
takes the path that is left when a link or a router is lost. A router's identity is
``router-0`` on the base host and ``router-r<i>`` on robot ``i``'s, each with its own
certificate; every router lets the others relay the run's traffic, and each checks its own
clients against the run's access policy.
"""

from __future__ import annotations

from dataclasses import dataclass

BASE = "base"
TOPOLOGIES = ("ring", "full", "star")


class MeshError(ValueError):
    """A router topology that cannot be used; the message names the link or host."""


def robot_host(robot: int) -> str:
    """The name of robot ``robot``'s host."""
    return f"r{robot}"


def host_names(robots: int) -> list[str]:
    """Every host of a team of ``robots``: the base first, then each robot's."""
    return [BASE] + [robot_host(i) for i in range(robots)]


def router_ident(host: str) -> str:
    """The router's identity suffix on ``host``: ``0`` on the base (the run's router), the host's name otherwise."""
    return "0" if host == BASE else host


def router_identities(robots: int, per_host: bool) -> list[str]:
    """The routers' identities of a run (``router-0``, and ``router-r<i>`` per robot host)."""
    return [f"router-{router_ident(h)}" for h in (host_names(robots) if per_host else [BASE])]


def links(spec: str, robots: int) -> list[tuple[str, str]]:
    """The router links of ``spec`` (``ring``, ``full``, ``star`` or ``a-b,c-d,...``) over the
    hosts of a team of ``robots``, each as (dialler, listener); raises MeshError for an unknown
    host, a link to itself, or a topology that leaves a host unreachable."""
    hosts = host_names(robots)
    spec = spec.strip()
    if spec == "ring":
        pairs = [(hosts[k], hosts[(k + 1) % len(hosts)]) for k in range(len(hosts) if len(hosts) > 2 else 1)]
    elif spec == "full":
        pairs = [(a, b) for k, a in enumerate(hosts) for b in hosts[k + 1:]]
    elif spec == "star":
        pairs = [(h, BASE) for h in hosts[1:]]
    else:
        pairs = []
        for item in filter(None, (part.strip() for part in spec.split(","))):
            a, sep, b = item.partition("-")
            if not sep or a not in hosts or b not in hosts:
                raise MeshError(f"router link {item!r}: name two of the hosts {', '.join(hosts)} as A-B "
                                f"(or give one of {', '.join(TOPOLOGIES)})")
            if a == b:
                raise MeshError(f"router link {item!r} links a host to itself")
            pairs.append((a, b))
    seen: set[frozenset[str]] = set()
    unique = [p for p in pairs if not (frozenset(p) in seen or seen.add(frozenset(p)))]
    if (cut := unreachable(hosts, unique)):
        raise MeshError(f"router links {spec!r} leave {', '.join(cut)} unreachable from {BASE}")
    return unique


def unreachable(hosts: list[str], pairs: list[tuple[str, str]], lost: frozenset[str] = frozenset()) -> list[str]:
    """The hosts (other than ``lost``) that cannot reach the base over ``pairs`` without the hosts in ``lost``."""
    reach, todo = {BASE}, [BASE]
    while todo:
        h = todo.pop()
        for a, b in pairs:
            for x, y in ((a, b), (b, a)):
                if x == h and y not in reach and y not in lost:
                    reach.add(y)
                    todo.append(y)
    return [h for h in hosts if h not in reach and h not in lost]


def single_points(robots: int, pairs: list[tuple[str, str]]) -> list[str]:
    """The robot hosts whose loss would cut another robot host off the base (none in a ring)."""
    hosts = host_names(robots)
    return [h for h in hosts[1:] if unreachable(hosts, pairs, frozenset({h}))]


@dataclass(frozen=True)
class HostRouter:
    """One host's router: where it listens, whom it dials, and where its own services find it."""

    host: str
    listen: tuple[str, ...]
    dial: tuple[str, ...]
    local: str  # the endpoint the host's services connect to

    @property
    def ident(self) -> str:
        return router_ident(self.host)


Address = tuple[str, int]


def plan(robots: int, spec: str, address: dict[str, Address], local: dict[str, Address] | None = None) -> dict[str, HostRouter]:
    """Every host's router for the links of ``spec``: ``address[host]`` is (address, port) where
    the other routers reach it, ``local[host]`` where the host's own services do (default: the
    same). Endpoints are TLS."""
    local = local or address

    def endpoint(host_port: Address) -> str:
        host, port = host_port
        return f"tls/{f'[{host}]' if ':' in host else host}:{port}"

    pairs = links(spec, robots)
    out = {}
    for h in host_names(robots):
        listen = tuple(dict.fromkeys([endpoint(address[h]), endpoint(local[h])]))
        dial = tuple(endpoint(address[b]) for a, b in pairs if a == h)
        out[h] = HostRouter(h, listen, dial, endpoint(local[h]))
    return out
