"""A run's kinds of service, each declared once: what it is called, one per robot or one per run,
its config section, the keys it speaks and reads, its command, and how ``up`` starts it.

Everything else is derived from these declarations: each service's identity and the router's
access policy (:mod:`swarmmap.shared.wire.secrets`), the ``swarmmap <service>`` subcommands, what
``swarmmap up`` starts (and on which host under ``--netns``), which crashed services it starts
again and how long each gets to stop, and the steps of the SLURM job (``swarmmap services``,
which deploy/slurm/team.sbatch reads); ``tests/deploy`` checks compose.yaml against them.

The kinds are plug-ins (group ``swarmmap.services``, swarmmap.shared.plugins): swarmmap's own
are named in its ``pyproject.toml`` and declared here; a package of one's own adds one with a
module holding its ``run(cfg, stop) -> int`` and an entry point naming its :class:`ServiceKind`
(docs/layout.md, "Adding a service").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from swarmmap.shared import plugins
from swarmmap.shared.wire.protocol import Keys


@dataclass(frozen=True)
class Access:
    """What the access policy needs to know of the run beyond a service's declaration."""

    robots: int
    neighbours: dict[int, set[int]] | None = None  # each robot's neighbours (None: a graph that changes)
    inproc_learner: bool = False  # one learner process serves every robot (as learner-0)
    host_routers: bool = False  # a router per host


def _none(keys: Keys, ident: int, run: Access) -> list[str]:
    return []


@dataclass(frozen=True)
class ServiceKind:
    """One kind of service.

    ``runner``: ``module:function`` of its main loop, ``function(cfg, stop) -> exit status`` (None
    for a tool that joins a run's session without being a service of it: ``up``, ``status``);
    ``per_robot``: one per robot (ids 0..robots-1), else one per run (id 0); ``section``: the
    config section its command line's flags set; ``speaks``/``reads``: the keys (beyond its own
    liveliness token, everyone's tokens and ``run/done``) it may publish, declare and answer on,
    and receive; ``up_order``: where ``swarmmap up`` starts it among the others (None: up does not
    start it as one of the run's services); ``instances``: which ids up starts (default: every
    robot's, or 0; None for one process that serves every robot, as an in-process learner);
    ``wait_alive``: up waits for its liveliness before the world drives;
    ``restart``: a crashed one is started again (``up.restarts`` times); ``grace``: the ``up``
    field of its time to stop (default ``stop_grace_s``); ``compute``: it trains (the SLURM job
    gives it CPUs of its own, and GPUs); ``ends_run``: the run is over when it exits (the
    recorder); ``optional``: the run goes on when it exits, whatever its status (the observer: a
    viewer that fails never fails a run); ``rank``: its place in listings (identities, the policy)."""

    summary: str
    runner: str | None
    per_robot: bool = False
    section: str | None = None
    speaks: Callable[[Keys, int, Access], list[str]] = _none
    reads: Callable[[Keys, int, Access], list[str]] = _none
    up_order: int | None = None
    instances: Callable[[Any], list[int | None]] | None = None
    wait_alive: bool = False
    restart: bool = False
    grace: str | None = None
    compute: bool = False
    ends_run: bool = False
    optional: bool = False
    rank: int = 100

    def ids(self, cfg: Any) -> list[int | None]:
        """The ids of this kind that ``up`` starts for ``cfg`` (a RunConfig)."""
        if self.instances is not None:
            return self.instances(cfg)
        return list(range(cfg.robots)) if self.per_robot else [0]


# ------------------------------------------------------------------ swarmmap's own kinds


def _learner_robots(ident: int, run: Access) -> list[int]:
    """The robots learner ``ident`` serves: its own, or every robot for the one in-process learner."""
    if run.inproc_learner:
        return list(range(run.robots)) if ident == 0 else []
    return [ident]


def _learner_speaks(keys: Keys, ident: int, run: Access) -> list[str]:
    return [k for i in _learner_robots(ident, run)
            for k in (keys.learner(i), keys.alive("learner", i), keys.alive("exchange", i), keys.alive("explore", i))]


def _learner_reads(keys: Keys, ident: int, run: Access) -> list[str]:
    out = []
    for i in _learner_robots(ident, run):
        peers = ["*"] if run.neighbours is None or run.inproc_learner else sorted(run.neighbours.get(i, set()))
        out += [keys.samples(i), keys.world_map(), *(k for j in peers for k in keys.exchange(j))]
        # exploration: the teammates' goals (a robot passes over those it would share), and its own and
        # their scans (the frontier policy's log-odds grid)
        out += [keys.scan(i), *(k for j in peers for k in (keys.goal(j), keys.scan(j)))]
    return out


ROUTER = ServiceKind("A Zenoh router for discovery across hosts and containers.", "swarmmap.services.router:run",
                     section="router", rank=0)
RECORDER = ServiceKind("The recorder: writes the run directory (config, metrics, summary, ground truth) and ends the run.",
                       "swarmmap.services.recorder:run", section="recorder",
                       speaks=lambda keys, i, run: [keys.run_done()],
                       reads=lambda keys, i, run: [keys.metrics("*"), keys.scan("*"), keys.world_map()],
                       up_order=10, wait_alive=True, ends_run=True, rank=1)
OBSERVER = ServiceKind("The Rerun observer: every learner's mean and std maps, the robots and the curves, live.",
                       "swarmmap.services.observer:run", section="observer",
                       reads=lambda keys, i, run: [keys.metrics("*"), keys.scan("*"), keys.state("*"), keys.goal("*"),
                                                   keys.world_map()],
                       up_order=20, instances=lambda cfg: [0] if cfg.up.observer else [], grace="observer_grace_s",
                       optional=True, rank=2)
WORLD = ServiceKind("The pybullet world: floor plan, robots on their paths, LiDAR scans, the ground-truth map.",
                    "swarmmap.services.world:run", section="world",
                    speaks=lambda keys, i, run: [keys.scan("*"), keys.world_map()],
                    reads=lambda keys, i, run: [keys.goal("*"), keys.metrics("*")],  # exploration: goals, the val_bce logged
                    up_order=50, restart=True, rank=3)
UP = ServiceKind("swarmmap up's own session: it watches the run's metrics and scans.", None,
                 reads=lambda keys, i, run: [keys.metrics("*"), keys.scan("*")], rank=4)
STATUS = ServiceKind("swarmmap status's session: a run's metrics, rounds and scans, never a State.", None,
                     reads=lambda keys, i, run: [keys.metrics("*"), keys.round_complete("*"), keys.scan("*")], rank=5)
LIDAR = ServiceKind("A LiDAR streamer: one robot's scans -> labelled training points.", "swarmmap.services.lidar:run",
                    per_robot=True, section="lidar",
                    speaks=lambda keys, i, run: [keys.samples(i)], reads=lambda keys, i, run: [keys.scan(i)],
                    up_order=40, wait_alive=True, restart=True, rank=6)
LEARNER = ServiceKind("A learner: DiNNO consensus training of one robot's occupancy network (Algorithm 1).",
                      "swarmmap.services.learner.service:run", per_robot=True, section="learner",
                      speaks=_learner_speaks, reads=_learner_reads, up_order=30,
                      instances=lambda cfg: [None] if cfg.learner.transport == "inproc" else list(range(cfg.robots)),
                      wait_alive=True, restart=True, grace="learner_grace_s", compute=True, rank=7)


# ------------------------------------------------------------------ the registry


def kinds() -> dict[str, ServiceKind]:
    """Every installed kind of service by name, in rank order (one per run first, then per robot)."""
    found = {p.name: plugins.load("services", p.name) for p in plugins.installed("services")}
    return dict(sorted(found.items(), key=lambda item: (item[1].per_robot, item[1].rank, item[0])))


def kind(name: str) -> ServiceKind:
    """The kind called ``name`` (a PluginError naming the close ones when none is)."""
    return plugins.load("services", name)


def started_by_up() -> list[tuple[str, ServiceKind]]:
    """The kinds ``up`` starts as the run's services, in its order (the routers are started before them)."""
    return sorted(((n, k) for n, k in kinds().items() if k.up_order is not None and k.runner), key=lambda nk: nk[1].up_order)


def identity(service: str, ident: int | str) -> str:
    """The identity of a service: ``learner-3``, ``world-0``."""
    return f"{service}-{ident}"


def identities(robots: int, host_routers: bool = False) -> list[str]:
    """Every identity of a run with ``robots`` robots: each kind's, one per run or one per robot;
    with ``host_routers`` also each robot host's router, ``router-r<i>`` (shared/wire/mesh.py)."""
    every = kinds()
    names = [identity(n, 0) for n, k in every.items() if not k.per_robot]
    names += [identity(n, i) for n, k in every.items() if k.per_robot for i in range(robots)]
    return names + ([identity("router", f"r{i}") for i in range(robots)] if host_routers else [])


def policy_keys(keys: Keys, run: Access) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
    """(speaks, reads) of every identity of the run: the keys it may publish, declare tokens and
    answer queries on (its own), and those it may receive (what its service reads, no more). Every
    member sees the liveliness tokens and ``run/done``; a host's router only relays."""
    every = kinds()
    speaks: dict[str, list[str]] = {}
    reads: dict[str, list[str]] = {}
    for name in identities(run.robots, run.host_routers):
        service, ident = name.rsplit("-", 1)
        speaks[name] = [keys.alive(service, ident)]
        reads[name] = [keys.alive(), keys.run_done()]
        if ident.isdigit():
            speaks[name] += every[service].speaks(keys, int(ident), run)
            reads[name] += every[service].reads(keys, int(ident), run)
    return ({n: sorted(set(k)) for n, k in speaks.items()}, {n: sorted(set(k)) for n, k in reads.items()})


def slurm_lines() -> list[str]:
    """What ``swarmmap services`` prints for deploy/slurm/team.sbatch: a line per kind the job
    starts beside its routers, ``NAME one|per-robot compute|light [ends-run]``, in up's order."""
    out = []
    for name, k in started_by_up():
        out.append(" ".join([name, "per-robot" if k.per_robot else "one", "compute" if k.compute else "light",
                             *(["ends-run"] if k.ends_run else [])]))
    return out
