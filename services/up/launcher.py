"""``swarmmap up``: the whole system as local processes on loopback, and its run directory.

First it checks what it can before anything exists (services/up/preflight.py: the plan and its
paths, the devices, the run directory, Zenoh's settings) and refuses with status 2, naming
the value and the fix. Then it starts a router on a free port, the recorder, the Rerun
observer (unless ``up.observer`` is off), then N learners and N lidar streamers (each its own
OS process, all Zenoh peers connected to the router, multicast scouting off) and the world, which
builds its plan meanwhile and drives once they are alive (``world.wait_for``).
The recorder (``swarmmap recorder``, the same service compose and SLURM start) writes the run
directory and ends the run: when every learner has finished, or one has failed, it says so on
``run/done`` and every service exits by itself; ``up`` returns the recorder's status. A
learner, lidar or world that crashes is started again (``up.restarts`` times each; a learner
resumes from its checkpoint and rejoins its team). A service that fails for good, or Ctrl-C,
stops the rest (in parallel, within ``up.stop_grace_s``); one that exits with status 2 refused
its settings, which would only repeat, and ends the run at once, its reason in ``summary.json``.
Services die with ``up``, even when it is killed (a parent-death signal). ``up`` adds every
service's pid, exit status and restarts to ``summary.json``. On its console it says each phase
(the plan, starting the services, the traversal, the training), one progress line of the team's
training, and a closing block: how the run ended, where its outputs are, what to run next.

Run directory: ``config.yaml`` (the resolved config; every service reads it), ``metrics.csv``,
``summary.json``, ``groundtruth.png`` and ``groundtruth.npz`` (grid and validation set),
``overview.png``, ``models/robot-<id>.pt``, ``maps/robot-<id>.*`` (the learned maps: arrays,
PNGs, a ROS map), ``data/robot-<id>.npz`` (training
points), ``logs/<service>-<id>.log``, ``recording.rrd`` and ``observer.json`` (the observer's
Rerun recording and its time per map).
A run directory is never overwritten: one that holds a finished run is refused, one that holds
a run that did not finish is resumed with ``--resume`` (``up.resume``: its learners go on from
their checkpoints, its metrics, summary and logs go on where they stopped) and refused without
it; ``prepare``, compose and the SLURM scripts keep the same rules (:func:`run_dir_problem`).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import yaml

from swarmmap.services.up.budget import Cgroups, checked_budgets
from swarmmap.services.up.budget import start_guard as start_budget_guard
from swarmmap.services.up.console import Console, closing_block
from swarmmap.services.up.netns import ROUTER_PORT, NetnsError, Network, free_subnet, start_guard, tag_of
from swarmmap.services.up.preflight import PlanFacts, check_run
from swarmmap.shared.run.atomic import atomic_write_text
from swarmmap.shared.run.config import Budget, ConfigError, RunConfig, fail, validate_config
from swarmmap.shared.run.disk import disk_words
from swarmmap.shared.run.fingerprint import fingerprint_diff, settings_fingerprint
from swarmmap.shared.run.progress import TeamProgress, TraversalProgress
from swarmmap.shared.run.rundir import RunDirBusy, config_doc, hold_run_dir, local_time, read_summary, run_state
from swarmmap.shared.run.runtime import die_with_parent
from swarmmap.shared.run.slots import slots_dir
from swarmmap.shared.wire.bus import Bus, Stopped
from swarmmap.shared.wire.mesh import BASE, HostRouter, MeshError, host_names, plan, robot_host
from swarmmap.shared.wire.protocol import Keys, Metrics, RunDone, Scan
from swarmmap.shared.wire.secrets import SecretsError, router_names, write_credentials
from swarmmap.shared.wire.services import identities, kinds, started_by_up
from swarmmap.shared.world.floorplan import PlanError
from swarmmap.shared.world.plans import plan_reference
from swarmmap.shared.world.recording import RecordingError, read_recording

log = logging.getLogger("up")

# How long after a service failed (for good) the recorder gets to end the run by itself (run/done).
# A service that exits with status 2 refused its settings: that would only repeat, so it ends the run at once.
FAILURE_GRACE_S = 30.0
REFUSED = 2


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prepare(cfg: RunConfig) -> RunConfig:
    """The run's resolved config, as every launcher writes it to ``RUN_DIR/config.yaml``: a run id
    and run directory, the recordings to replay or record, and an observer that the world waits
    for and that saves ``RUN_DIR/recording.rrd``."""
    if cfg.up.resume and cfg.run_dir is None and cfg.run_id == "default":
        raise ConfigError("config error:\n  up.resume: name the run to resume: --run-dir RUN_DIR (or --run-id ID for runs/ID)")
    run_id = cfg.run_id
    if run_id == "default":  # a resumed run keeps its id
        run_id = (cfg.up.resume and config_doc(cfg.run_dir).get("run_id")) or time.strftime("run-%Y%m%d-%H%M%S")
    run_dir = (cfg.run_dir or Path("runs") / run_id).resolve()
    secrets = None if cfg.zenoh.insecure else (cfg.zenoh.secrets or run_dir / "secrets").resolve()
    cfg = cfg.model_copy(update={"run_id": run_id, "run_dir": run_dir,
                                 "zenoh": cfg.zenoh.model_copy(update={"secrets": secrets})})
    if cfg.world.dataset:  # every service finds the logs wherever it starts (SLURM tasks, a resumed run)
        world = cfg.world.model_copy(update={"dataset": [str(Path(p).expanduser().resolve()) for p in cfg.world.dataset]})
        cfg = cfg.model_copy(update={"world": world})
    if cfg.up.replay is not None:
        cfg = replay_config(cfg, cfg.up.replay)
    if cfg.up.record is not None:
        record = str(cfg.up.record.resolve() / "robot-{robot}.swrec")
        cfg = cfg.model_copy(update={"lidar": cfg.lidar.model_copy(update={"record": record})})
    if cfg.up.observer:
        obs = cfg.observer.model_copy(update={"save": cfg.observer.save or run_dir / "recording.rrd",
                                              "spawn": cfg.observer.spawn or cfg.up.viewer,
                                              "mcap": cfg.observer.mcap or (run_dir / "bag" if cfg.up.mcap else None)})
        wait_for = cfg.world.wait_for + ([] if "observer" in cfg.world.wait_for else ["observer"])
        cfg = cfg.model_copy(update={"observer": obs, "world": cfg.world.model_copy(update={"wait_for": wait_for})})
    return cfg


def host_cores() -> int:
    """The cores this process may run on (its affinity: a container's or a SLURM job's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def write_config(cfg: RunConfig, router_endpoints: list[str] | None = None) -> Path:
    """Write ``RUN_DIR/config.yaml`` and, unless the run is insecure, the run's credentials;
    returns the config's path."""
    path = cfg.run_dir / "config.yaml"
    atomic_write_text(path, cfg.dump_yaml())
    write_run_secrets(cfg, router_endpoints)
    return path


def write_run_secrets(cfg: RunConfig, router_endpoints: list[str] | None = None) -> None:
    """The run's credentials in ``zenoh.secrets``: a folder per service with its own key, its
    certificate and the run's CA certificate (shared/wire/secrets.py); the routers' certificates
    name the hosts of ``zenoh.connect`` and of ``router_endpoints`` (where the routers of a
    run with a router per host reach each other). The CA key is discarded once they are
    issued, or kept in ``zenoh.keep_ca``, which must lie outside what services read."""
    if cfg.zenoh.insecure:
        log.warning("INSECURE run %s: no TLS, no authentication, no access control (--zenoh-insecure)", cfg.run_id)
        return
    if cfg.zenoh.signer is not None:  # compose: each service makes its own key and asks the run's signer
        return
    secrets, keep = cfg.zenoh.secrets.resolve(), cfg.zenoh.keep_ca
    if keep is not None and any(keep.resolve().is_relative_to(p) for p in (secrets, cfg.run_dir.resolve() if cfg.run_dir else secrets)):
        fail(f"config error:\n  zenoh.keep_ca: {keep} lies inside the credentials or the run directory, which services read; "
             "keep the CA key elsewhere (e.g. ~/.swarmmap-ca)")
    try:
        issued = write_credentials(secrets, cfg.run_id, identities(cfg.robots, cfg.router_per_host()),
                                   router_names(cfg.zenoh.connect + (router_endpoints or []), cfg.router.hosts), keep_ca=keep)
    except (SecretsError, OSError) as exc:
        fail(f"config error:\n  zenoh.secrets: {exc}")
    if issued:
        kept = f"kept in {keep}" if keep is not None else "discarded"
        log.info("credentials of run %s: %d services, each its own key in %s/<service>@%s (owner only); the CA key is %s",
                 cfg.run_id, len(issued), secrets, cfg.run_id, kept)


def run_secrets(cfg: RunConfig, stop: threading.Event) -> int:
    """``swarmmap secrets``: write the run's credentials (for services started by hand)."""
    if cfg.zenoh.secrets is None:
        fail("config error:\n  zenoh.secrets: name the folder (--zenoh-secrets) or the run directory (--run-dir)")
    write_run_secrets(cfg)
    print(cfg.zenoh.secrets)
    return 0


@dataclass
class Child:
    """One service process (the latest, when it was restarted)."""

    service: str
    ident: int | str
    proc: subprocess.Popen
    log_path: Path
    args: tuple[str, ...] = ()
    restarts: int = 0
    host: list[str] | None = None  # the command prefix that runs it on its host (a network namespace)
    robot: int | None = None  # the robot it serves (its host's router: that robot's), None for the base host's services

    @property
    def name(self) -> str:
        return f"{self.service}-{self.ident}"



class Interrupted(Exception):
    """Ctrl-C (or SIGTERM) while ``up`` waited for the services to start."""


def optional(child: Child) -> bool:
    """Whether the run goes on when ``child`` exits (the observer)."""
    k = kinds().get(child.service)
    return k is not None and k.optional

class Launcher:
    """Starts, watches and stops the services of one run; with a ``console`` it shows the run's
    progress and ends with the closing block (``swarmmap up``), without one it only logs."""

    def __init__(self, cfg: RunConfig, stop: threading.Event, console: Console | None = None):
        self.stop = stop
        self.console = console
        self.router_endpoint = f"tcp/127.0.0.1:{free_port()}"
        zenoh = cfg.zenoh.model_copy(update={"mode": "peer", "connect": [self.router_endpoint],
                                             "listen": ["tcp/127.0.0.1:0"], "multicast_scouting": False})
        cfg = cfg.model_copy(update={"zenoh": zenoh})
        if cfg.learner.compute_slots is None and cfg.learner.transport == "zenoh" and cfg.robots > (cores := host_cores()):
            # every learner on this host, more than its cores: each round's training in turns, not sliced (shared/run/slots.py)
            cfg = cfg.model_copy(update={"learner": cfg.learner.model_copy(update={"compute_slots": cores})})
        self.cfg = prepare(cfg)
        self.run_dir = self.cfg.run_dir
        self.keys = Keys(self.cfg.key_prefix, self.cfg.run_id)
        self.children: list[Child] = []
        self.gone: set[str] = set()  # optional services that exited, told of once
        self.config_path = self.run_dir / "config.yaml"
        self.team = TeamProgress(self.cfg.robots, self.cfg.learner.rounds)
        self.traversal = TraversalProgress(self.cfg.robots)
        self.failure: str | None = None  # why up ended the run, for summary.json (a refusal, a service that failed)
        self.failure_code: int | None = None  # that service's exit status
        self.done: RunDone | None = None  # the recorder's verdict, as it said it (also when it could not write it)
        self._phase = "starting"
        self.per_host = self.cfg.router_per_host()
        self.network: Network | None = None  # up --netns: the run's hosts
        self.routers: dict[str, HostRouter] = {}  # a router per host: where each listens, whom it dials
        if self.per_host:
            self.plan_hosts()
        self.cgroups: Cgroups | None = None  # up.budget: a control group per robot (services/up/budget.py)
        self._budget_at = 0.0  # when budget.json was last written
        self._t0 = time.monotonic()

    def plan_hosts(self) -> None:
        """A router per host (shared/wire/mesh.py): on loopback ports, or with ``up.netns`` on the
        addresses of the run's network (services/up/netns.py)."""
        cfg, base_port = self.cfg, int(self.router_endpoint.rsplit(":", 1)[1])
        hosts = host_names(cfg.robots)
        local = {BASE: ("127.0.0.1", base_port)}
        if cfg.up.netns:
            if os.geteuid() != 0:
                raise ConfigError("config error:\n  up.netns: network namespaces need root (run up as root, or drop --netns "
                                  "for a router per host on loopback: --routers per-host)")
            self.network = Network(cfg.run_id, cfg.robots, self.run_dir / "network.json", rate=cfg.up.link_rate,
                                   loss=cfg.up.link_loss)
            try:
                self.network.subnet = str(free_subnet(tag_of(cfg.run_id)))
            except NetnsError as exc:
                raise ConfigError(f"config error:\n  up.netns: {exc}") from None
            address = {h: (self.network.address(h), base_port if h == BASE else ROUTER_PORT) for h in hosts}
            local |= {h: ("127.0.0.1", ROUTER_PORT) for h in hosts[1:]}
        else:
            address = local = local | {h: ("127.0.0.1", free_port()) for h in hosts[1:]}
        try:
            self.routers = plan(cfg.robots, cfg.up.router_links, address, local)
        except MeshError as exc:
            raise ConfigError(f"config error:\n  up.router_links: {exc}") from None

    def router_endpoints(self) -> list[str]:
        """Every endpoint a router of the run listens on (their certificates name these hosts)."""
        return [e for r in self.routers.values() for e in r.listen]

    def on_host(self, robot: int | None, client: bool) -> tuple[list[str] | None, tuple[str, ...]]:
        """The command prefix and the extra arguments of a service of robot ``robot`` (None: the
        base host's): with a router per host, a robot's services (a ``client``) are clients of
        their own router only."""
        if not self.per_host or robot is None:
            return None, ()
        host = robot_host(robot)
        prefix = self.network.prefix(host) if self.network is not None else None
        return prefix, ("--set", f"zenoh.connect=[{self.routers[host].local}]") if client else ()

    def spawn(self, service: str, ident: int | str, *extra: str, robot: int | None = None) -> Child:
        """Start ``swarmmap <service>`` reading the run's config.yaml, logging to logs/ (appended:
        a resumed run's log goes on after the earlier ones, under a line that says so); a
        service of ``robot`` runs on that robot's host."""
        prefix, more = self.on_host(robot, client=service != "router")
        child = Child(service, ident, None, self.run_dir / "logs" / f"{service}-{ident}.log", (*extra, *more), host=prefix,
                      robot=robot)
        if child.log_path.exists() and child.log_path.stat().st_size:
            with child.log_path.open("a") as out:
                out.write(f"\n--- swarmmap up: run {self.cfg.run_id} resumed at {local_time(time.time())} ---\n")
        self.start(child, "a")
        self.children.append(child)
        return child

    def start(self, child: Child, mode: str) -> None:
        cmd = [*(child.host or []), sys.executable, "-m", "swarmmap.services.cli", child.service, "--config", str(self.config_path),
               *child.args]
        # The config file already holds the resolved environment; children must not re-read it.
        env = {k: v for k, v in os.environ.items() if not k.startswith("SWARMMAP_") and k != "SLURM_PROCID"}
        env["PYTHONUNBUFFERED"] = "1"
        join = self.cgroups.joiner(child.robot) if self.cgroups is not None and child.robot is not None else None

        def before() -> None:  # (in the child, before it runs the service)
            die_with_parent()
            if join is not None:
                join()

        with child.log_path.open(mode) as out:
            child.proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                          preexec_fn=before)

    def restart(self, child: Child) -> None:
        """Start a crashed service again (a learner resumes from its checkpoint and rejoins)."""
        child.restarts += 1
        log.warning("%s exited with status %s; restarting it (%d of %d). Its log (%s) ends:\n%s", child.name,
                    child.proc.returncode, child.restarts, self.cfg.up.restarts, child.log_path, tail(child.log_path, 5))
        with child.log_path.open("a") as out:
            out.write(f"\n--- swarmmap up: restart {child.restarts} after exit status {child.proc.returncode} ---\n")
        self.start(child, "a")

    def over_budget(self, child: Child) -> bool:
        """Whether ``child`` was killed at its robot's memory budget (``up.budget``)."""
        return (self.cgroups is not None and child.robot is not None and child.proc.returncode == -9
                and self.cgroups.oom_kills(child.robot) > 0)

    def reason(self, child: Child) -> str:
        """Why ``child`` ended, for summary.json (:func:`failure_reason`; its memory budget where that killed it)."""
        if self.over_budget(child):
            return (f"{child.name} was killed at robot {child.robot}'s memory budget ({self.cgroups.budgets[child.robot]}): give the "
                    "robots more (--budget) or a smaller model")
        return failure_reason(child)

    def failed(self) -> Child | None:
        """A service that exited with an error (an optional one, the observer, is told of once and
        the run goes on without it)."""
        for c in self.children:
            if c.proc.poll() in (None, 0):
                continue
            if not optional(c):
                return c
            if c.name not in self.gone:
                self.gone.add(c.name)
                log.warning("%s exited with status %s; the run goes on without it (it is optional). Its log (%s) ends:\n%s",
                            c.name, c.proc.returncode, c.log_path, tail(c.log_path, 5))
        return None

    def wait_alive(self, bus: Bus, service: str, idents: set[str]) -> None:
        """Wait until ``service`` ``idents`` are alive; raises RuntimeError when one exited or none came in time."""
        deadline = time.monotonic() + self.cfg.up.start_timeout_s
        while not self.stop.is_set():
            missing = idents - {i for _, i in bus.alive(service)}
            if not missing:
                return
            if (bad := self.failed()) is not None:
                self.failure, self.failure_code = self.reason(bad), bad.proc.returncode
                raise RuntimeError(f"{bad.name} exited with status {bad.proc.returncode} while starting; "
                                   f"see {bad.log_path}:\n{tail(bad.log_path)}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{service} {sorted(missing)} not alive after {self.cfg.up.start_timeout_s:.0f} s")
            self.stop.wait(0.1)
        raise Interrupted

    def grace(self, child: Child) -> float:
        """How long ``child`` gets to finish once the run is over: the observer maps the final
        States, a learner writes its model and maps; the others only close."""
        k = kinds().get(child.service)
        return getattr(self.cfg.up, k.grace if k is not None and k.grace else "stop_grace_s")

    def let_leave(self, alive: Callable[[], set[str]]) -> None:
        """Wait until every service but the router has exited by itself, at most its grace time. A
        service restarted that is not up again (``alive()``: the names with a liveliness token,
        asked only when a restarted service still runs) once the recorder has gone will never hear
        the run's end (``run/done``): it gets no grace, :meth:`shutdown` stops it."""
        restarted = {c.name for c in self.children if c.restarts and c.proc.poll() is None}
        up = alive() if restarted else set()
        start = time.monotonic()
        for c in self.children:
            if c.service == "router" or (c.name in restarted and c.name not in up):
                continue
            try:
                c.proc.wait(max(0.0, start + self.grace(c) - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass

    def shutdown(self) -> None:
        """SIGTERM every service still running, all at once (the router last, as the others may
        still talk through it); SIGKILL what has not stopped within its grace time."""
        for group in ([c for c in self.children if c.service != "router"], [c for c in self.children if c.service == "router"]):
            running = [c for c in group if c.proc.poll() is None]
            for c in running:
                c.proc.terminate()
            start = time.monotonic()
            for c in running:  # stopped, a learner leaves its outputs: only the observer keeps its long grace
                grace = self.cfg.up.observer_grace_s if c.service == "observer" else self.cfg.up.stop_grace_s
                try:
                    c.proc.wait(max(0.0, start + grace - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop within %.0f s; killing it", c.name, grace)
                    c.proc.kill()
                    c.proc.wait()

    def run(self) -> int:
        """Check the run, then start every service and watch them until the run is over; returns
        0 (every learner finished), 1 (it failed, also when a service refused its settings), 130 (interrupted)."""
        cfg = self.cfg
        facts = check_run(cfg, endpoints=False, observer=cfg.up.observer)  # raises before anything exists
        self.traversal.expected = facts.expected_scans
        self.announce(facts)
        budgets = self.fitted_budgets(facts)  # (refused before anything is written)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        budget_guard = None
        if budgets:
            self.cgroups = Cgroups(cfg.run_id, budgets)  # (a ConfigError where it cannot)
            budget_guard = start_budget_guard(self.cgroups, self.run_dir / "logs" / "budget-guard.log")
            log.info("each robot's services in a budget of %s (cgroup %s)", budgets[0] if len(set(budgets)) == 1 else
                     "; ".join(f"robot {i}: {b}" for i, b in enumerate(budgets)), "v2" if self.cgroups.v2 else "v1")
        write_config(cfg, self.router_endpoints())
        t0 = self._t0 = time.monotonic()
        status = 1
        guard = None
        try:
            if self.network is not None:
                guard = start_guard(self.network.state_path, self.run_dir / "logs" / "netns-guard.log")
                self.network.create()
            self.start_routers()
            with Bus.open(cfg.zenoh, self.keys, "up", 0, stop=self.stop) as bus:
                bus.subscribe(self.keys.metrics("*"), Metrics, self.on_metrics, newest=1024)  # progress: never slows a publisher
                bus.subscribe(self.keys.scan("*"), Scan, self.traversal.add, newest=1024)
                bus.subscribe(self.keys.run_done(), RunDone, self.on_done, sender_from_key=False)
                recorder = self.start_services(bus, t0)
                status = self.watch(recorder)
                if status != 130 and self.failure_code != REFUSED:  # the run is over: the services leave by themselves
                    self.let_leave(lambda: {f"{service}-{ident}" for service, ident in bus.alive()})  # (run/done)
        except (Interrupted, Stopped):
            log.info("interrupted while the services started; stopping every service")
            status = 130
        except RuntimeError as exc:
            log.error("%s", exc)
            status = 1
        except NetnsError as exc:
            log.error("up --netns: %s", exc)
            self.failure, status = f"the run's network could not be made: {exc}", 1
        finally:
            if self.stop.is_set() and status != 0:  # Ctrl-C: a service that died of it too is no failure of the run
                status = 130
            self.shutdown()
            if self.network is not None:
                self.network.remove()
            if guard is not None:
                guard.terminate()
            if cfg.learner.compute_slots:
                shutil.rmtree(slots_dir(cfg.run_id), ignore_errors=True)
            self.complete_summary(time.monotonic() - t0, status)
            if self.cgroups is not None:
                self.cgroups.close()
            if budget_guard is not None:
                budget_guard.terminate()
            if self.console is not None:
                self.console.close()
                print(closing_block(self.run_dir), flush=True)
        return status

    def fitted_budgets(self, facts: PlanFacts) -> list[Budget]:
        """Each robot's budget, checked against what its services need (:func:`checked_budgets`)."""
        if self.cfg.up.budget and self.cfg.learner.transport == "inproc":
            raise ConfigError("config error:\n  up.budget: a budget is per robot, and learner.transport inproc runs "
                              "every robot's learner in one process; use the zenoh transport")
        return checked_budgets(self.cfg, facts.path_lengths_m, facts.expected_scans, facts.size_m, self.per_host)

    def announce(self, facts: PlanFacts) -> None:
        """The run's plan, settings and directory, before anything starts."""
        cfg, s = self.cfg, self.cfg.learner
        log.info("run %s: %d robots, %d rounds, model %s %s (%s, %s transport) on device %s%s", cfg.run_id, cfg.robots, s.rounds,
                 s.model, s.model_shape, s.algorithm, s.transport, s.device, f", preset {cfg.preset}" if cfg.preset else "")
        log.info("%s", facts.describe())
        log.info("run directory: %s", self.run_dir)

    def start_services(self, bus: Bus, t0: float) -> Child:
        """Start the run's services in the registry's order (swarmmap.shared.wire.services: the recorder,
        the observer, the learners, the lidar streamers, the world, then any other kind up starts)
        and wait until those that must be are alive (the world builds its plan meanwhile and drives
        once they are: ``world.wait_for``); returns the service that ends the run (the recorder)."""
        plan = [(name, k, k.ids(self.cfg)) for name, k in started_by_up()]
        names = ["router"] + [f"{len(ids)} {name}(s)" if k.per_robot else name for name, k, ids in plan if ids]
        log.info("starting %d services: %s", 1 + sum(len(ids) for _, _, ids in plan), ", ".join(names))
        self.wait_alive(bus, "router", {r.ident for r in self.routers.values()} or {"0"})
        ends = None
        for name, k, ids in plan:  # the recorder first, so that it records the run from the start
            for i in ids:  # None: one process serves every robot (an in-process learner), on the base host
                child = self.spawn(name, 0) if i is None or not k.per_robot else self.spawn(name, i, "--robot", str(i), robot=i)
                if k.ends_run:
                    ends = child
        robots = {str(i) for i in range(self.cfg.robots)}
        for name, k, ids in plan:
            if k.wait_alive and ids:
                self.wait_alive(bus, name, robots if k.per_robot else {"0"})
        log.info("every service but the world is alive after %.1f s; the world builds the plan and drives the robots",
                 time.monotonic() - t0)
        return ends

    def start_routers(self) -> None:
        """The run's router, or with a router per host each host's, linked as ``up.router_links`` says."""
        if not self.per_host:
            self.spawn("router", 0, "--zenoh-mode", "router", "--zenoh-listen", self.router_endpoint, "--set", "zenoh.connect=[]")
            return
        for host, r in self.routers.items():
            self.spawn("router", r.ident, "--ident", r.ident, "--zenoh-mode", "router", "--set", f"zenoh.listen=[{','.join(r.listen)}]",
                       "--set", f"zenoh.connect=[{','.join(r.dial)}]", robot=None if host == BASE else int(host[1:]))
        links = ", ".join(f"{h}->{d.split('/')[-1]}" for h, r in self.routers.items() for d in r.dial)
        log.info("a router per host (%d), linked %s: %s", len(self.routers), self.cfg.up.router_links, links)

    def restartable(self, child: Child) -> bool:
        """A crashed learner, lidar or world is started again; with a router per host, a router
        too (its host's services reconnect to it and rejoin)."""
        k = kinds().get(child.service)
        return (k is not None and k.restart) or (self.per_host and child.service == "router")

    def show_progress(self, force: bool = False) -> None:
        """Log each phase once as it begins, and draw the progress line of the current one
        (at once when a phase begins, or with ``force``)."""
        phase = self._phase
        if self.team.started and phase != "training":
            if self.traversal.started:
                log.info("%s", self.traversal.line())
            log.info("training: %d learner(s), %d rounds of Algorithm 1", self.cfg.robots, self.cfg.learner.rounds)
            self._phase = "training"
        elif self.traversal.started and phase == "starting":
            log.info("traversal: the robots drive their paths")
            self._phase = "traversal"
        if self.console is not None:
            line = self.team.line() if self._phase == "training" else self.traversal.line()
            self.console.progress(line, force=force or phase != self._phase)

    def on_done(self, msg: RunDone) -> None:
        """The recorder's verdict on ``run/done``."""
        self.done = msg

    def on_metrics(self, m: Metrics) -> None:
        """One learner's Metrics: into the team's progress (each robot's line in the debug log)."""
        self.team.add(m)
        log.debug("robot %d round %4d  val_bce %.4f  consensus %.4f%s", m.sender, m.round, m.val_bce,
                  m.consensus_error, "  (final)" if m.final else "")

    def watch(self, recorder: Child) -> int:
        """Wait until the recorder says the run is over (it exits 0 or 1). A service that fails
        gives the recorder FAILURE_GRACE_S to end the run (``run/done``) before ``up`` stops it;
        one that refuses its settings (status 2) ends the run at once."""
        failed_at = None
        while not self.stop.is_set():
            code = recorder.proc.poll()
            if code is not None and code != REFUSED:
                self.show_progress(force=True)  # the team's last line
                if code == 0:
                    log.info("the run is over: every learner finished")
                else:
                    why = self.done.reason if self.done is not None else "the recorder said nothing on run/done"
                    log.error("the run failed (recorder status %d): %s; see %s", code, why, self.run_dir / "summary.json")
                return 0 if code == 0 else 1
            for c in self.children:  # a crash is retried; a refusal (status 2: settings, checkpoint, plan) would only repeat
                if self.restartable(c) and c.proc.poll() not in (None, 0, REFUSED) and c.restarts < self.cfg.up.restarts \
                        and not self.over_budget(c):  # (at its memory limit it would only be killed again)
                    self.restart(c)
            if (refused := next((c for c in self.children if c.proc.poll() == REFUSED and not optional(c)), None)) is not None:
                self.failure, self.failure_code = failure_reason(refused), REFUSED
                log.error("%s; ending the run now (a refusal would only repeat). Its log (%s) ends:\n%s",
                          self.failure, refused.log_path, tail(refused.log_path))
                return 1
            if failed_at is None and (bad := self.failed()) is not None and bad is not recorder:  # its verdict: above
                log.error("%s exited with status %s; ending the run. Its log (%s) ends:\n%s",
                          bad.name, bad.proc.returncode, bad.log_path, tail(bad.log_path))
                failed_at, self.failure, self.failure_code = time.monotonic(), self.reason(bad), bad.proc.returncode
            if failed_at is not None and time.monotonic() - failed_at > FAILURE_GRACE_S:
                return 1
            self.show_progress()
            self.write_budget()
            self.stop.wait(0.2)
        log.info("interrupted; stopping every service")
        return 130

    def write_budget(self, every_s: float = 2.0) -> None:
        """Each robot's memory and CPU against its budget, into ``RUN_DIR/budget.json`` every
        ``every_s`` (``swarmmap status`` shows it)."""
        now = time.monotonic()
        if self.cgroups is None or now - self._budget_at < every_s:
            return
        self._budget_at = now
        try:
            atomic_write_text(self.run_dir / "budget.json", json.dumps(self.cgroups.live(now - self._t0)) + "\n")
        except OSError as exc:
            log.warning("could not write %s: %s", self.run_dir / "budget.json", exc.strerror)

    def complete_summary(self, wall: float, status: int) -> None:
        """Add every service's pid and exit status to the recorder's ``summary.json``."""
        path = self.run_dir / "summary.json"
        try:
            summary = json.loads(path.read_text())
        except (OSError, ValueError):  # the recorder never got to write it
            summary = {"run_id": self.cfg.run_id, "preset": self.cfg.preset, "robots": self.cfg.robots,
                       "rounds": self.cfg.learner.rounds, "ok": False, "reason": "the recorder wrote no summary",
                       "started": time.time() - wall, "learners": {}}
        if status == 130:  # stopped by its user: the recorder was stopped too, and says the run was cut short
            summary.update(ok=False, reason=f"interrupted (Ctrl-C or SIGTERM) after {wall:.0f} s; resume it with "
                                            f"swarmmap up --run-dir {self.run_dir} --resume")
        elif self.failure is not None and status != 0:  # why up ended the run, which the recorder could not know
            summary.update(ok=False, reason=self.failure)
        learners = {c.ident: c for c in self.children if c.service == "learner"}
        for robot, entry in summary.get("learners", {}).items():
            c = learners.get(int(robot)) or learners.get(0)  # in-process: learner-0 serves every robot
            if c is not None:
                entry.update(pid=c.proc.pid, exit_code=c.proc.returncode)
        summary["status"] = status
        if self.cgroups is not None:
            summary["budget"] = self.cgroups.report(wall)
        summary["wall_time_s"] = round(wall + summary.get("earlier_wall_time_s", 0.0), 3)  # a resumed run's attempts add up
        summary["services"] = {c.name: {"pid": c.proc.pid, "exit_code": c.proc.returncode, "restarts": c.restarts}
                               for c in self.children}
        if self.per_host:  # where each host's router listened and whom it dialled
            summary["hosts"] = {h: {"router": f"router-{r.ident}", "listen": list(r.listen), "links": list(r.dial),
                                    **({"namespace": self.network.namespace(h)} if self.network and h != BASE else {})}
                                for h, r in self.routers.items()}
        try:
            atomic_write_text(path, json.dumps(summary, indent=2) + "\n")
        except OSError as exc:
            log.error("could not write %s: %s (%s)", path, exc.strerror, disk_words(self.run_dir))
            return
        log.info("summary: %s", path)


def replay_config(cfg: RunConfig, folder: Path) -> RunConfig:
    """The run's config for replaying the recordings in ``folder``: robots, seed, world and
    sensor settings come from the recordings; the world only serves the map."""
    files = sorted(folder.glob("robot-*.swrec"))
    if not files:
        raise RecordingError(folder, "no robot-<i>.swrec recordings in this folder")
    recs = {}
    for f in files:
        rec = read_recording(f, allow_incomplete=cfg.lidar.replay_incomplete)
        recs[rec.robot] = rec
    if sorted(recs) != list(range(len(recs))):
        raise RecordingError(folder, f"recordings of robots {sorted(recs)}; expected robots 0..{len(recs) - 1}")
    try:
        recorded = validate_config(recs[0].config)
    except ConfigError as exc:
        raise RecordingError(files[0], f"its recorded config is refused here: {exc.message.splitlines()[-1].strip()}") from None
    plan = recs[0].header.get("plan", {})
    if plan.get("sha256") and plan_reference(plan["floorplan"]).get("sha256") != plan["sha256"]:
        raise RecordingError(folder, f"the recorded floor plan {plan['floorplan']} is missing or has changed since")
    world = recorded.world.model_copy(update={"drive": False})
    lidar = recorded.lidar.model_copy(update={"record": None, "robot": None, "replay": str(folder.resolve() / "robot-{robot}.swrec"),
                                              "replay_speed": cfg.lidar.replay_speed,
                                              "replay_incomplete": cfg.lidar.replay_incomplete})
    return cfg.model_copy(update={"robots": len(recs), "seed": recorded.seed, "world": world, "lidar": lidar})


def tail(path: Path, lines: int = 15) -> str:
    """The last lines of a log file."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


LOG_PREFIX = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ ([A-Z]+) [\w.-]+: ")  # setup_logging's time, level, service


def last_error(lines: list[str]) -> str:
    """The last error a service said in ``lines`` of its log: its last ERROR record (with the
    lines it spans) or ``config error`` block, else the last line of a traceback, else its last lines."""
    starts = [i for i, line in enumerate(lines) if (m := LOG_PREFIX.match(line)) and m.group(1) in ("ERROR", "CRITICAL")
              or line.startswith("config error")]
    if starts:
        end = next((j for j in range(starts[-1] + 1, len(lines)) if LOG_PREFIX.match(lines[j])), len(lines))
        block = lines[starts[-1] : min(end, starts[-1] + 8)]
    elif any(line.startswith("Traceback") for line in lines):
        block = [next(line for line in reversed(lines) if line.strip())]
    else:
        block = lines[-3:]
    return " ".join(LOG_PREFIX.sub("", line).strip() for line in block if line.strip())


def failure_reason(child: Child) -> str:
    """Why ``child`` ended: its exit status and its log's last error (what it said, without the
    log's time stamps), for summary.json."""
    lines = [line for line in tail(child.log_path, 60).splitlines() if not line.startswith("pybullet build time")]
    said = last_error(lines)[:600] or "(its log is empty)"
    verb = "refused to run" if child.proc.returncode == REFUSED else "failed"
    return f"{child.name} {verb} (exit status {child.proc.returncode}): {said}"


def run_prepare(cfg: RunConfig, stop: threading.Event) -> int:
    """``swarmmap prepare``: check the run as ``up`` would (its run directory too), then write its
    config.yaml (and its credentials) and print its path; nothing is written when a check fails."""
    try:
        cfg = prepare(cfg)
    except (RecordingError, PlanError) as exc:
        log.error("%s", exc)
        return 2
    try:
        with hold_run_dir(cfg.run_dir, "swarmmap prepare"):
            if (why := run_dir_problem(cfg)) is not None:
                log.error("refusing to prepare: %s", why)
                return 2
            facts = check_run(cfg, endpoints=True)
            checked_budgets(cfg, facts.path_lengths_m, facts.expected_scans, facts.size_m, cfg.router_per_host())
            print(write_config(cfg))
    except RunDirBusy as exc:
        log.error("refusing to prepare: %s", exc)
        return 2
    return 0


@dataclass(frozen=True)
class WayOut:
    """How a user of one launcher names another run directory, and asks for a resume."""

    other: str = "choose another --run-dir"
    resume: str = "--resume"


def run_dir_problem(cfg: RunConfig, ways: WayOut = WayOut()) -> str | None:
    """Why ``cfg.run_dir`` cannot take this run, naming the way out; None when it can. A finished
    run is never overwritten; an interrupted one is resumed only when asked (``up.resume``), and
    only by a run with its settings (:func:`~swarmmap.shared.run.fingerprint.settings_fingerprint`)."""
    run_dir, state = cfg.run_dir, run_state(cfg.run_dir)
    if state == "new":
        if cfg.up.resume:
            log.info("%s holds no run to resume: this run starts afresh there", run_dir)
        return None
    if state == "finished":
        ended = local_time((read_summary(run_dir) or {}).get("finished"))
        return (f"{run_dir} holds a finished run{f' (it ended {ended})' if ended else ''}, which is never overwritten; "
                f"{ways.other}, or move that one away")
    if cfg.explore.active:  # (its learners' checkpoints hold their rounds, not where the robots were)
        return (f"{run_dir} holds an exploring run that did not finish ({unfinished_words(run_dir)}): an exploration "
                f"cannot be resumed (the drive, the robots' positions, goals and what they saw, is not checkpointed); "
                f"{ways.other} to explore again")
    if not cfg.up.resume:
        return f"{run_dir} holds a run that did not finish ({unfinished_words(run_dir)}); resume it with {ways.resume}, or {ways.other}"
    return other_settings_in(cfg, ways)


def unfinished_words(run_dir: Path) -> str:
    """How the run in ``run_dir`` ended without finishing, from its summary."""
    summary = read_summary(run_dir)
    if summary is None:
        return "no summary: it is still running, or it stopped without one"
    if summary.get("status") == 130:
        return "it was interrupted"
    reason = str(summary.get("reason", ""))
    return f"it failed: {reason[:200]}{'...' if len(reason) > 200 else ''}"


def other_settings_in(cfg: RunConfig, ways: WayOut = WayOut()) -> str | None:
    """Why ``cfg.run_dir`` cannot be resumed by this run: its config holds other settings (its
    checkpoints would be refused and its outputs mixed with another run's); None when it can."""
    path = cfg.run_dir / "config.yaml"
    if not path.exists():
        return None  # the checkpoints, if any, carry their own fingerprints
    try:
        old = validate_config(yaml.safe_load(path.read_text()) or {})
    except ConfigError as exc:
        return f"{path} holds a config this version refuses ({exc.message.splitlines()[-1].strip()}); {ways.other}"
    except Exception as exc:  # noqa: BLE001 - any unreadable config is named, never overwritten
        return f"{path} cannot be read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
    if (diff := fingerprint_diff(settings_fingerprint(old), settings_fingerprint(cfg))) == "":
        return None
    return f"{cfg.run_dir} holds a run with other settings ({diff}); {ways.other}, or remove it to start afresh"


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """``swarmmap up``: check the run, start it, show its progress, end with the closing block."""
    try:
        launcher = Launcher(cfg, stop, Console())
    except (RecordingError, PlanError) as exc:
        log.error("%s", exc)
        return 2
    try:
        with hold_run_dir(launcher.cfg.run_dir, "swarmmap up"):
            if (why := run_dir_problem(launcher.cfg)) is not None:
                log.error("refusing to start: %s", why)
                return 2
            return launcher.run()
    except RunDirBusy as exc:
        log.error("refusing to start: %s", exc)
        return 2
