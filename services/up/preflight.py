"""What ``swarmmap up`` and ``swarmmap prepare`` check before they start or write anything.

The plan loads (with the loaders the world uses), its waypoints exist and there is one path per
robot (or paths can be planned), the torch devices exist on this machine, Zenoh's endpoints and
config file are usable, the run directory (and a recording folder) can be written (a file is
really written there: a read-only or full disk is refused), a graph file exists. Every problem
found is reported at once, each naming the value and the fix, as one ConfigError (exit status
2), before a run directory, credentials or a process exist.

    facts = check_run(cfg, endpoints=True)   # cfg as prepared (its run_dir resolved)
    print(facts.describe())                  # plan, rooms, size, path lengths, coverage
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from swarmmap.shared.run.config import ConfigError, RunConfig, ZenohSettings, did_you_mean
from swarmmap.shared.run.disk import existing, write_problem
from swarmmap.shared.run.sections import parse_extent

# Zenoh's link protocols, and those whose address is host:port.
PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
HOST_PORT = ("tcp", "udp", "tls", "quic", "ws")
PLAN_SUFFIXES = (".svg", ".png", ".yaml", ".yml")


@dataclass
class PlanFacts:
    """What the console says about the run's plan and paths before the world drives them."""

    name: str
    kind: str
    rooms: int
    size_m: tuple[float, float]
    path_lengths_m: list[float] = field(default_factory=list)
    coverage: float | None = None  # share of free space within LiDAR range of a path
    waypoints: str | None = None  # the waypoint folder; None: paths planned through the plan
    expected_scans: int = 0  # over every robot: its path's length / speed x scan rate
    dataset: str | None = None  # a run on real logs: what they give

    def describe(self) -> str:
        """``plan 353 (cubicasa): 12 rooms, 14.2 x 9.8 m; paths 20.1, 18.7 m (planned); coverage 97%``."""
        if self.dataset is not None:
            if self.kind == "ros2":
                return f"robots {self.name}: {self.dataset}"
            return f"dataset {self.name}: {self.dataset}; map {self.size_m[0]:.1f} x {self.size_m[1]:.1f} m"
        text = f"plan {self.name} ({self.kind}): {self.rooms} room(s), {self.size_m[0]:.1f} x {self.size_m[1]:.1f} m"
        if self.path_lengths_m:
            source = f"waypoints from {self.waypoints}" if self.waypoints else "planned through the plan"
            text += f"; paths {', '.join(f'{v:.1f}' for v in self.path_lengths_m)} m ({source})"
        if self.coverage is not None:
            text += f"; free space within LiDAR range of a path: {100 * self.coverage:.0f}%"
        return text


def endpoint_problem(where: str, endpoint: str) -> str | None:
    """Why a Zenoh endpoint (``tcp/10.0.0.5:7447``) cannot be used, or None."""
    proto, sep, address = endpoint.partition("/")
    example = "e.g. tcp/10.0.0.5:7447"
    if not sep or not address:
        return f"{where}: {endpoint!r} is not an endpoint: write <protocol>/<address>, {example}"
    if proto not in PROTOCOLS:
        return f"{where}: {endpoint!r}: unknown protocol {proto!r}{did_you_mean(proto, PROTOCOLS)}; one of {', '.join(PROTOCOLS)}"
    if proto in HOST_PORT:
        hostport = address.split("?")[0].split("#")[0]
        host, colon, port = hostport.rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            return f"{where}: {endpoint!r}: the address must be host:port with a port 0-65535, {example}"
    return None


def zenoh_problems(z: ZenohSettings, endpoints: bool) -> list[str]:
    """Endpoints that do not parse (``endpoints``: the run uses the configured ones) and a Zenoh
    config file that is missing or that Zenoh cannot read."""
    problems = []
    if endpoints:
        for name in ("connect", "listen"):
            problems += [p for e in getattr(z, name) if (p := endpoint_problem(f"zenoh.{name}", e)) is not None]
    if z.config_file is not None and not z.config_file.is_file():
        problems.append(f"zenoh.config_file: {z.config_file} does not exist; name a Zenoh JSON5 file or leave it unset")
    if problems:
        return problems
    import zenoh

    from swarmmap.shared.wire.bus import zenoh_config

    try:  # Zenoh's own reading of the file and endpoints (security is checked as the services start)
        zenoh_config(z.model_copy(update={"insecure": True}), "up")
    except zenoh.ZError as exc:
        problems.append(f"zenoh: Zenoh refuses these settings: {str(exc).split(' at /')[0]}")
    return problems


def device_problem(where: str, name: str) -> str | None:
    """Why torch device ``name`` does not exist on this machine, or None (auto always does)."""
    if name in ("auto", "cpu"):
        return None
    import torch

    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        return f"{where}: {name!r} is not a torch device; use auto, cpu, cuda or cuda:<index>"
    if device.type == "cuda":
        if not torch.cuda.is_available():
            return (f"{where}: {name!r}, but this machine has no CUDA device (torch {torch.__version__}); "
                    f"use auto or cpu (--device cpu)")
        if device.index is not None and device.index >= (n := torch.cuda.device_count()):
            return f"{where}: {name!r}, but this machine has {n} CUDA device(s), cuda:0 to cuda:{n - 1}"
    elif device.type == "mps":
        if not torch.backends.mps.is_available():
            return f"{where}: {name!r}, but this machine has no Apple GPU (mps); use auto or cpu"
    elif device.type != "cpu":
        return f"{where}: {name!r}: swarmmap runs on cpu, cuda or mps devices"
    return None


def writable_problem(where: str, path: Path) -> str | None:
    """Why folder ``path`` cannot be created or written by this user, or None: a file is really
    written and removed in it (or in its nearest existing ancestor), so that a read-only disk and a
    full one are found too, for root as for anyone (nothing is left behind)."""
    if path.exists() and not path.is_dir():
        return f"{where}: {path} is a file, not a folder; choose another"
    probe = existing(path)
    if not probe.is_dir():
        return f"{where}: {path} lies under {probe}, which is a file; choose another folder"
    if (why := write_problem(probe)) is not None:
        made = "" if probe == path else f", so {path} cannot be made there"
        return f"{where}: {why}{made}; choose another folder"
    return None


def plan_hint(spec: str) -> str:
    """`` (did you mean ...?)`` for a missing plan: a plan file of the same folder, or procedural."""
    path = Path(spec)
    choices = ["procedural"] if "/" not in spec else []
    if path.parent.is_dir():
        choices += [str(path.parent / p.name) if path.parent != Path(".") else p.name
                    for p in path.parent.iterdir() if p.suffix.lower() in PLAN_SUFFIXES]
    return did_you_mean(spec, choices)


def plan_facts(cfg: RunConfig) -> PlanFacts:
    """Load the run's plan and, when the world drives, its paths, as the world will; raises
    PlanError naming the file and the problem."""
    from swarmmap.shared.world.paths import coverage, path_length
    from swarmmap.shared.world.plans import load_floorplan, robot_paths

    w = cfg.world
    plan = load_floorplan(w.floorplan, w, cfg.seed)
    x0, y0, x1, y1 = plan.bounds
    facts = PlanFacts(plan.name, plan.kind, len(plan.rooms), (x1 - x0, y1 - y0), waypoints=w.waypoints)
    if w.drive:
        grid = plan.occupancy(w.grid_resolution_m)
        paths = robot_paths(cfg, plan, grid)
        facts.path_lengths_m = [path_length(p) for p in paths]
        facts.coverage = coverage(paths, grid, w.lidar_max_range_m)
        facts.expected_scans = sum(int(v / w.speed_mps * w.lidar_rate_hz) + 1 for v in facts.path_lengths_m)
    return facts


def dataset_facts(cfg: RunConfig) -> PlanFacts:
    """Read the run's logs and cut them into robots as the world will; raises DatasetError."""
    import numpy as np

    from swarmmap.shared.world.datasets import BagTopics, read_log
    from swarmmap.shared.world.teams import split_team

    w = cfg.world
    logs = [read_log(p, w.dataset_pose, BagTopics(w.dataset_scan_topic, w.dataset_odom_topic, w.dataset_fixed_frame))
            for p in w.dataset]
    team = split_team(logs, cfg.robots, w.dataset_holdout_every)
    ends = np.concatenate([lg.endpoints(w.lidar_max_range_m) for lg in logs] + [lg.poses[:, :2] for lg in logs])
    size = tuple(float(v) for v in ends.max(0) - ends.min(0) + 2 * w.dataset_margin_m)
    counts = [len(r.train) for r in team]
    text = (f"{sum(map(len, logs))} scans of {', '.join(str(len(lg.angles)) for lg in logs)} beams; {cfg.robots} robots of "
            f"{min(counts)}-{max(counts)} training scans (every {w.dataset_holdout_every}th scan held out for validation)")
    return PlanFacts(", ".join(Path(p).name for p in w.dataset), "dataset", 0, size, expected_scans=sum(counts), dataset=text)


def check_run(cfg: RunConfig, *, endpoints: bool, observer: bool = True) -> PlanFacts:
    """Every check above on the prepared ``cfg``; returns what the plan looks like, or raises
    one ConfigError listing every problem. ``endpoints``: the run uses the configured Zenoh
    endpoints (prepare; up puts its own loopback ones in); ``observer``: one will run."""
    from swarmmap.shared.world.floorplan import PlanError

    problems = zenoh_problems(cfg.zenoh, endpoints)
    problems += [p for where, name in (("learner.device", cfg.learner.device),
                                       *((("observer.device", cfg.observer.device),) if observer else ()))
                 if (p := device_problem(where, name)) is not None]
    secrets = None if cfg.zenoh.insecure or cfg.zenoh.secrets is None or cfg.zenoh.secrets.is_relative_to(cfg.run_dir) \
        else cfg.zenoh.secrets  # in the run directory, checked with it
    problems += [p for where, path in (("run_dir", cfg.run_dir), ("up.record", cfg.up.record), ("zenoh.secrets", secrets))
                 if path is not None and (p := writable_problem(where, path)) is not None]
    if cfg.learner.graph == "file" and cfg.learner.graph_file is not None and not cfg.learner.graph_file.is_file():
        problems.append(f"learner.graph_file: {cfg.learner.graph_file} does not exist; name a YAML/JSON list of [i, j] edges")
    facts = None
    if cfg.ros2.live:  # (the robots are heard once the world starts)
        if problems:
            raise ConfigError("refusing to start (nothing was created):\n" + "\n".join(f"  {p}" for p in problems))
        box = parse_extent(cfg.ros2.extent) if cfg.ros2.extent else None
        size = (box[2] - box[0], box[3] - box[1]) if box else (0.0, 0.0)
        where = f"map {size[0]:.1f} x {size[1]:.1f} m (ros2.extent)" if box else "map: what their first scans see"
        return PlanFacts(", ".join(f"/{ns}" for ns in cfg.ros2.namespaces), "ros2", 0, size,
                         dataset=f"ROS 2 robots heard live; {where}")
    if cfg.world.dataset:
        from swarmmap.shared.world.datasets import DatasetError

        try:
            facts = dataset_facts(cfg)
        except DatasetError as exc:
            problems.append(f"world.dataset: {exc}")
        if problems:
            raise ConfigError("refusing to start (nothing was created):\n" + "\n".join(f"  {p}" for p in problems))
        return facts
    try:
        facts = plan_facts(cfg)
    except PlanError as exc:
        where = "world.waypoints" if cfg.world.waypoints and str(exc.path).startswith(str(cfg.world.waypoints)) else "world.floorplan"
        missing = where == "world.floorplan" and not Path(cfg.world.floorplan).exists()
        hint = plan_hint(cfg.world.floorplan) + "; give procedural, a CubiCasa5K model.svg, a DiNNO .png or a ROS map_server .yaml" \
            if missing else ""
        problems.append(f"{where}: {exc}{hint}")
    if problems:
        raise ConfigError("refusing to start (nothing was created):\n" + "\n".join(f"  {p}" for p in problems))
    return facts
