"""``swarmmap observer``: watch a run's maps form, live, in Rerun.

The observer subscribes to the world's ground-truth plan, every robot's scans, and every
learner's State and Metrics. For each learner it evaluates the parameters of its newest State
on a grid (``observer.map_resolution_m``) and logs the mean map and, for a Bayesian network,
the standard-deviation map from ``observer.mc_samples`` Monte-Carlo passes, on the ``round``
timeline, every ``observer.map_every`` rounds (by default the rounds the learners report their
metrics for) and at the final round. Map evaluation runs in its own thread, apart from message intake: when States come
faster than maps can be computed, the older ones are dropped and the newest State of each
learner is mapped next (counted as ``skipped``). The time per map is logged and reported.

Entities (pixel coordinates of the map grid, north up):

- ``world/plan``: the ground-truth occupancy (static); ``world/robots/<i>/pose``,
  ``world/robots/<i>/trajectory`` and ``world/robots/<i>/scan`` (latest scan's hits), on the
  ``sim_time`` timeline (and on ``round`` at the newest round reported so far); ``world/graph``: the communication graph between the robots.
  A trajectory is logged in pieces of at most ``TRAJECTORY_PIECE`` points: a scan re-logs only
  the newest piece (``trajectory``), finished ones stay as ``trajectory/<k>``, and a robot that
  moved less than half a map cell adds no point, so the recording grows with the path's length,
  not with its square.
- ``maps/mean/robot-<i>`` and ``maps/std/robot-<i>``: colour images, on ``round``.
- ``curves/val_bce/robot-<i>``, ``curves/consensus/robot-<i>``: the learners' metrics, on
  ``round``; ``observer/map_time_s``: seconds per map.

Sinks, any of them together: ``observer.save`` (an .rrd file; ``swarmmap up`` saves
``RUN_DIR/recording.rrd``; one there already, a resumed run's, is kept and this recording goes
to ``recording-2.rrd``), ``observer.spawn`` (a local viewer), ``observer.connect`` (a viewer
at a gRPC URL) and ``observer.serve_web`` (the web viewer, for containers and remote machines).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from swarmmap.shared.learning.bnn import fast_bf16, predict_mean_std
from swarmmap.shared.learning.graphs import GraphError, run_graph
from swarmmap.shared.learning.layout import StateLayout
from swarmmap.shared.learning.models import StochasticNet, pick_device, set_flat
from swarmmap.shared.learning.networks import build_network, has_std
from swarmmap.shared.run.atomic import atomic_write_text
from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.overview import OCCUPANCY_CMAP, STD_CMAP, colorize
from swarmmap.shared.run.rosout import MapSink, McapBag
from swarmmap.shared.run.rundir import unused_path
from swarmmap.shared.run.runtime import die_with_parent
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.compression import Decompressor
from swarmmap.shared.wire.protocol import Goal, Keys, Metrics, ProtocolError, Scan, State, WorldMap
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.sensing import beam_ends

log = logging.getLogger("swarmmap.observer")
WATCH_RING = 1024  # scans and metrics that may wait for the observer before the oldest are dropped
FINAL_STATES_WAIT_S = 10.0  # once the run is over, how long the learners' final States may take to arrive
TRAJECTORY_PIECE = 100  # points of a robot's trajectory logged at once (the newest piece)

ROBOT_COLOURS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                          [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)


def colour(robot: int) -> np.ndarray:
    return ROBOT_COLOURS[robot % len(ROBOT_COLOURS)]


def blueprint(robots: int, bayesian: bool) -> rrb.Blueprint:
    """Plan and robots with the curves under them, a grid of mean maps, a grid of std maps."""
    cols = int(np.ceil(np.sqrt(robots)))
    left = rrb.Vertical(
        rrb.Spatial2DView(origin="world", name="plan and robots"),
        rrb.TimeSeriesView(origin="curves/val_bce", name="validation BCE"),
        rrb.TimeSeriesView(origin="curves/consensus", name="consensus error"),
        row_shares=[2, 1, 1])
    means = rrb.Grid(*[rrb.Spatial2DView(origin=f"maps/mean/robot-{i}", name=f"mean {i}") for i in range(robots)],
                     grid_columns=cols, name="mean maps")
    parts = [left, means]
    if bayesian:
        parts.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"maps/std/robot-{i}", name=f"std {i}") for i in range(robots)],
                              grid_columns=cols, name="std maps"))
    return rrb.Blueprint(rrb.Horizontal(*parts), collapse_panels=True)


LOOPBACK = ("127.0.0.1", "::1", "localhost")


def rerun_executable() -> list[str]:
    """Rerun's viewer binary itself (``RERUN_CLI_PATH``, else the one ``rerun-sdk`` ships), so that
    stopping the process started stops the server; ``python -m rerun`` where there is none (that
    wrapper runs the binary as a child of its own, which outlives the wrapper when it is stopped)."""
    if path := os.environ.get("RERUN_CLI_PATH"):
        return [path]
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
        if binary.is_file() and sys.platform != "darwin":
            return [str(binary)]
    except ImportError:
        pass
    return [sys.executable, "-m", "rerun"]


def rerun_cli(*args: str, detach: bool = False) -> subprocess.Popen:
    """Rerun's CLI with ``ARGS`` (its own viewer and servers, which take a bind address): dying
    with this process, or, ``detach``-ed, staying open after it (a viewer window)."""
    return subprocess.Popen([*rerun_executable(), *args], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=detach, preexec_fn=None if detach else die_with_parent)


def check_bind(bind: str) -> None:
    """Warn when the observer's servers listen beyond this machine."""
    if bind not in LOOPBACK:
        inside = " (in a container: only as far as its engine publishes the ports)" if Path("/.dockerenv").exists() else ""
        log.warning("observer.bind %s: the web viewer and its gRPC server listen beyond loopback%s; whoever reaches them sees "
                    "the run's plan, poses, scans and maps, and may log into the stream", bind, inside)


def open_sinks(cfg: RunConfig, rec: rr.RecordingStream, bp: rrb.Blueprint) -> tuple[list[str], list[subprocess.Popen]]:
    """Attach every sink the config asks for; returns their descriptions and the Rerun processes
    started for them (a local viewer, the web viewer's server), to stop at the end. Servers
    listen on ``observer.bind`` (loopback unless told otherwise)."""
    s = cfg.observer
    sinks, names, procs = [], [], []
    if s.save is not None:
        s.save.parent.mkdir(parents=True, exist_ok=True)
        save = unused_path(s.save)  # a resumed run keeps the recording of its earlier attempt
        sinks.append(rr.FileSink(str(save)))
        names.append(f"file {save}")
    if s.spawn:
        rerun_cli("--port", str(s.grpc_port), "--bind", "127.0.0.1", detach=True)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{s.grpc_port}/proxy"))
        names.append(f"spawned viewer on port {s.grpc_port}")
    if s.connect:
        sinks.append(rr.GrpcSink(s.connect))
        names.append(f"viewer at {s.connect}")
    if s.serve_web:
        check_bind(s.bind)
        sinks.append(rr.GrpcServerSink(bind_ip=s.bind, port=s.grpc_port))
        names.append(f"web viewer http://{s.bind}:{s.web_port} (gRPC {s.grpc_port})")
    if not sinks:
        raise ConfigError("config error:\n  observer: no sink; set observer.save, observer.spawn, observer.connect "
                          "or observer.serve_web")
    rec.set_sinks(*sinks, default_blueprint=bp)
    if s.serve_web:  # the page only (the data stays on the gRPC server above), from Rerun's CLI, which binds where told
        host = "127.0.0.1" if s.bind in ("0.0.0.0", "::") else s.bind
        procs.append(rerun_cli("--serve-web", "--bind", s.bind, "--web-viewer-port", str(s.web_port),
                               f"rerun+http://{host}:{s.grpc_port}/proxy"))
    return names, procs


class Trajectory:
    """A robot's path as the observer logs it: the newest piece (at most ``piece`` points) and
    how many pieces came before it; a point closer than ``min_step`` to the last one is not added."""

    def __init__(self, min_step: float, piece: int = TRAJECTORY_PIECE):
        self.min_step, self.piece = min_step, piece
        self.done = 0  # finished pieces
        self.points: list[list[float]] = []

    def add(self, x: float, y: float) -> tuple[bool, list[list[float]] | None]:
        """Add a pose: whether the newest piece changed, and the piece this finished (when the
        newest was full; the next one starts where it ended)."""
        if self.points and np.hypot(x - self.points[-1][0], y - self.points[-1][1]) < self.min_step:
            return False, None
        finished = None
        if len(self.points) >= self.piece:
            finished, self.points = self.points, self.points[-1:]
            self.done += 1
        self.points.append([x, y])
        return True, finished


@dataclass(frozen=True)
class Snapshot:
    """A learner's State as the observer keeps it: its round and its vector (rebuilt if compressed)."""

    sender: int
    round: int
    params: np.ndarray


class Observer:
    """Message intake (Zenoh callback threads) and map evaluation (:meth:`map_loop`), one recording."""

    def __init__(self, cfg: RunConfig, rec: rr.RecordingStream, device: torch.device, sinks: list[MapSink] | None = None):
        self.cfg, self.rec, self.device = cfg, rec, device
        self.sinks = sinks or []  # where the maps go besides Rerun: a rosbag2, ROS 2 topics
        self.s = cfg.observer
        self.map_every = self.s.map_every or cfg.report_every()
        self.last_round = cfg.rounds()
        bf16 = self.s.map_dtype == "bf16" or (self.s.map_dtype == "auto" and fast_bf16(device or "cpu"))
        self.map_dtype = torch.bfloat16 if bf16 else torch.float32
        self.lock = threading.Lock()
        self.wake = threading.Condition(self.lock)
        self.newest: dict[int, Snapshot] = {}  # newest unmapped State per learner
        self.seen_round: dict[int, int] = {}  # newest State round received per learner
        self.decompressor = Decompressor()
        self.mapped_round: dict[int, int] = {}
        self.trajectories: dict[int, Trajectory] = {}
        self.positions: dict[int, np.ndarray] = {}
        self.scans_seen: dict[int, int] = {}
        self.states_in = self.skipped = 0
        self.latest_round = 0  # the newest round any learner reported: world entities are logged at it
        self.map_times: list[float] = []
        self.grid: OccupancyGrid | None = None
        self.model: torch.nn.Module | None = None
        self.layout: StateLayout | None = None
        self.points = np.zeros((0, 2), np.float32)
        self.shape = (0, 0)
        self.graph: dict[int, set[int]] = {}

    # ------------------------------------------------------------------ intake
    def on_world(self, world: WorldMap) -> None:
        """The plan, the map grid and the model the States are evaluated with."""
        raw = world.grid.numpy()  # 0 free, 1 occupied, 2 unknown (a dataset's reference, a ROS map's unknown)
        unknown = raw == 2
        grid = OccupancyGrid(raw, world.resolution, tuple(world.origin), unknown=unknown if unknown.any() else None)
        self.grid = grid.resample(self.s.map_resolution_m)
        self.points, self.shape = grid.centres(self.s.map_resolution_m)
        self.points = self.points.astype(np.float32)
        model = build_network(self.cfg.network(), world.bounds, self.cfg.seed).to(self.device)
        self.layout = StateLayout.of(model, self.cfg.state_copies())  # DSGT's State carries its tracker too, RAMEN's its counts
        self.model = model
        self.rec.log("world/plan", rr.Image(colorize(self.grid.grid.astype(float), OCCUPANCY_CMAP, 1.0)), static=True)
        unknown = self.grid.unknown if self.grid.unknown is not None else np.zeros(self.grid.grid.shape, bool)
        trinary = np.where(unknown, 2, self.grid.grid).astype(np.uint8)[: self.shape[0], : self.shape[1]]
        for sink in self.sinks:
            sink.world(self.s.map_resolution_m, self.grid.origin, self.shape, trinary)
        positions = world.positions.numpy() if world.positions is not None else None
        try:
            self.graph = run_graph(self.cfg.graph(), self.cfg.robots, positions)
        except GraphError as exc:
            log.warning("no communication graph to show: %s", exc)
        if positions is not None:
            self.positions = {i: p for i, p in enumerate(positions)}
        log.info("map grid %d x %d at %.3f m, model %s with %d parameters", self.shape[1], self.shape[0],
                 self.s.map_resolution_m, self.cfg.network().kind, self.layout.param_count)

    def pixel(self, xy: np.ndarray) -> np.ndarray:
        """World metres (N, 2) -> image pixels (N, 2) of the map grid, north up."""
        res, (ox, oy) = self.s.map_resolution_m, self.grid.origin
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.stack([(xy[:, 0] - ox) / res, self.shape[0] - (xy[:, 1] - oy) / res], axis=1)

    def on_scan(self, scan: Scan) -> None:
        if self.grid is None:
            return
        i = scan.sender
        n = self.scans_seen.get(i, 0)
        self.scans_seen[i] = n + 1
        hit = scan.hit.numpy().astype(bool)
        for sink in self.sinks:
            if sink.every_scan:
                sink.scan(i, scan.pose, scan.angles.numpy(), scan.ranges.numpy(), hit, scan.max_range)
        if n % self.s.scan_every and not scan.last:
            return
        x, y, _ = scan.pose
        self.positions[i] = np.array([x, y])
        hits = beam_ends(scan.pose, scan.angles.numpy(), scan.ranges.numpy(), hit)
        c = colour(i)
        self.rec.set_time("sim_time", duration=scan.t)
        self.rec.set_time("round", sequence=self.latest_round)  # so the plan view shows the robots on either timeline
        self.rec.log(f"world/robots/{i}/pose", rr.Points2D(self.pixel([x, y]), radii=4, colors=c, labels=str(i)))
        self.log_trajectory(i, x, y)
        self.rec.log(f"world/robots/{i}/scan", rr.Points2D(self.pixel(hits), radii=1.5, colors=c))
        self.log_graph()
        for sink in self.sinks:
            if not sink.every_scan:
                sink.scan(i, scan.pose, scan.angles.numpy(), scan.ranges.numpy(), hit, scan.max_range)

    def log_trajectory(self, i: int, x: float, y: float) -> None:
        """Log the newest piece of robot ``i``'s trajectory (and a piece it finished, for good)."""
        path = self.trajectories.setdefault(i, Trajectory(self.s.map_resolution_m / 2))
        changed, finished = path.add(x, y)
        if finished is not None:
            self.rec.log(f"world/robots/{i}/trajectory/{path.done - 1}", rr.LineStrips2D([self.pixel(np.array(finished))],
                                                                                         colors=colour(i)))
        if changed:
            self.rec.log(f"world/robots/{i}/trajectory", rr.LineStrips2D([self.pixel(np.array(path.points))], colors=colour(i)))

    def on_goal(self, goal: Goal) -> None:
        """Exploring: the robot's goal for the next leg and the path its learner planned to it."""
        if self.grid is None:
            return
        i, c = goal.sender, colour(goal.sender)
        if goal.done or goal.path is None:
            self.rec.log(f"world/robots/{i}/goal", rr.Clear(recursive=True))
            return
        self.rec.log(f"world/robots/{i}/goal", rr.Points2D(self.pixel([goal.x, goal.y]), radii=5, colors=c,
                                                           labels=f"{i}: leg {goal.leg}"))
        self.rec.log(f"world/robots/{i}/goal/path", rr.LineStrips2D([self.pixel(goal.path.numpy())], colors=c, radii=0.5))

    def log_graph(self) -> None:
        edges = [self.pixel(np.array([self.positions[i], self.positions[j]]))
                 for i, nbrs in self.graph.items() for j in nbrs if i < j and i in self.positions and j in self.positions]
        self.rec.log("world/graph", rr.LineStrips2D(edges, colors=[120, 120, 120]))

    def on_metrics(self, m: Metrics) -> None:
        self.latest_round = max(self.latest_round, m.round)
        self.rec.set_time("round", sequence=m.round)
        self.rec.log(f"curves/val_bce/robot-{m.sender}", rr.Scalars(m.val_bce))
        self.rec.log(f"curves/consensus/robot-{m.sender}", rr.Scalars(m.consensus_error))

    def on_state(self, msg: State) -> None:
        """Keep the newest State of each learner; a State superseded before it was mapped is skipped.
        A compressed State is rebuilt first (every one of a topk chain is needed)."""
        vec = msg.params.numpy() if msg.plain else self.decompressor.vector(msg)
        if vec is None:
            return
        before = self.seen_round.get(msg.sender, -1)
        self.seen_round[msg.sender] = max(before, msg.round)
        if before < msg.round != self.last_round and msg.round // self.map_every <= before // self.map_every:
            return  # no map round since the last State: mapping every State would take the CPU the learners need
        with self.lock:
            self.states_in += 1
            old = self.newest.get(msg.sender)
            if msg.round <= self.mapped_round.get(msg.sender, -1) or (old is not None and old.round >= msg.round):
                return  # a duplicate or late State
            if old is not None:
                self.skipped += 1
            self.newest[msg.sender] = Snapshot(msg.sender, msg.round, vec)
            self.wake.notify()

    def check_state(self, msg: State) -> None:
        """Refuse a State this run's model cannot hold."""
        why = self.layout.refuses(msg.vector_size) if self.layout is not None else None
        if why is not None:
            raise ProtocolError("shape", why)

    # ------------------------------------------------------------------ maps
    def map_state(self, msg: Snapshot) -> float:
        """Log the mean (and std) map of one State; returns the seconds it took."""
        t0 = time.perf_counter()
        flat = torch.from_numpy(self.layout.params_of(msg.params).copy()).to(self.device)
        set_flat(self.model, flat)
        mean, std = predict_mean_std(self.model, self.points, samples=self.s.mc_samples, seed=msg.round,
                                     dtype=self.map_dtype)
        h, w = self.shape
        self.rec.set_time("round", sequence=msg.round)
        self.rec.log(f"maps/mean/robot-{msg.sender}", rr.Image(colorize(mean.reshape(h, w), OCCUPANCY_CMAP, 1.0)))
        stochastic = isinstance(self.model, StochasticNet)
        if stochastic:
            self.rec.log(f"maps/std/robot-{msg.sender}", rr.Image(colorize(std.reshape(h, w), STD_CMAP, self.s.std_max)))
        for sink in self.sinks:
            sink.maps(msg.sender, mean.reshape(h, w), std.reshape(h, w) if stochastic else None)
        dt = time.perf_counter() - t0
        self.rec.log("observer/map_time_s", rr.Scalars(dt))
        return dt

    def map_loop(self, stop: threading.Event) -> None:
        """Map the newest State of each learner, oldest round first, until ``stop``; then map
        whatever is still waiting (the final States) and return."""
        while True:
            with self.lock:
                while not self.newest and not stop.is_set():
                    self.wake.wait(0.2)
                if not self.newest:
                    return
                robot = min(self.newest, key=lambda r: self.newest[r].round)
                msg = self.newest.pop(robot)
                self.mapped_round[robot] = msg.round
            if self.model is None:
                continue
            try:
                self.map_times.append(self.map_state(msg))
            except Exception:  # one bad map must not end the observer: say so and go on
                log.exception("robot %d round %d: could not map this State", robot, msg.round)
                continue
            log.debug("robot %d round %d mapped in %.3f s", robot, msg.round, self.map_times[-1])

    def has_final_states(self) -> bool:
        """Whether every learner's final State has arrived (mapped or waiting to be)."""
        last = self.last_round
        with self.lock:
            got = {r for r, k in self.mapped_round.items() if k >= last} | {r for r, m in self.newest.items() if m.round >= last}
        return got >= set(range(self.cfg.robots))

    def report(self) -> dict:
        t = np.array(self.map_times) if self.map_times else np.zeros(1)
        return {"maps": len(self.map_times), "map_dtype": str(self.map_dtype).removeprefix("torch."),
                "states_received": self.states_in, "states_skipped": self.skipped,
                "map_time_mean_s": round(float(t.mean()), 4), "map_time_max_s": round(float(t.max()), 4),
                "last_round_mapped": self.mapped_round}


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The observer's main work; returns the process exit status."""
    s = cfg.observer
    torch.set_num_threads(s.torch_threads)
    device = pick_device(s.device)
    rec = rr.RecordingStream("swarmmap", recording_id=cfg.run_id)
    bp = blueprint(cfg.robots, has_std(cfg.network().kind))
    sinks, servers = open_sinks(cfg, rec, bp)
    log.info("observer of run %s: %s", cfg.run_id, "; ".join(sinks))
    try:
        return observe(cfg, stop, rec, device)
    finally:
        for proc in servers:
            proc.terminate()
            proc.wait()


def observe(cfg: RunConfig, stop: threading.Event, rec: rr.RecordingStream, device: torch.device) -> int:
    """Watch the run until it is over, then write observer.json; returns the exit status."""
    keys = Keys(cfg.key_prefix, cfg.run_id)
    sinks: list[MapSink] = []
    try:
        if cfg.observer.mcap is not None:
            sinks.append(McapBag(unused_path(cfg.observer.mcap), cfg.observer.std_max))  # a resumed run keeps its earlier bag
            log.info("writing the run as a rosbag2 (MCAP) to %s", sinks[-1].path)
        if (namespaces := cfg.ros2_maps()) is not None:
            from swarmmap.shared.run.rosmaps import Ros2Maps

            seen = cfg.run_dir / "maps" / "ros2-seen.npz" if cfg.run_dir is not None else None
            sinks.append(Ros2Maps(namespaces, cfg.observer.std_max, cfg.ros2.unknown_std, seen))
            log.info("publishing the maps to ROS 2: %s and /map (nav_msgs/OccupancyGrid, transient local)",
                     ", ".join(f"/{ns}/map" for ns in namespaces))
        return watch(cfg, keys, Observer(cfg, rec, device, sinks), stop)
    finally:
        for sink in sinks:
            sink.close()  # (closed already when the run ended well)


def watch(cfg: RunConfig, keys: Keys, obs: Observer, stop: threading.Event) -> int:
    """Observe the run through ``obs`` until it is over; returns the exit status."""
    rec = obs.rec
    mapping_done = threading.Event()
    worker = threading.Thread(target=obs.map_loop, args=(mapping_done,), name="maps")
    with Bus.open(cfg.zenoh, keys, "observer", 0) as bus:
        bus.end_with_run(stop)
        world = bus.world(cfg.world_wait_s(), stop)
        if world is None:
            return 0 if stop.is_set() else 3
        obs.on_world(world)
        # A watcher: behind rings, so that logging to Rerun never slows the world or the learners.
        bus.subscribe(keys.scan("*"), Scan, obs.on_scan, newest=WATCH_RING)
        bus.subscribe(keys.metrics("*"), Metrics, obs.on_metrics, newest=WATCH_RING)
        bus.subscribe(keys.goal("*"), Goal, obs.on_goal, newest=WATCH_RING)
        bus.subscribe(keys.state("*"), State, obs.on_state, check=obs.check_state, newest=max(8, 2 * cfg.robots))
        bus.announce(0)
        worker.start()
        stop.wait()
        if bus.run_done is not None and bus.run_done.ok:  # the final States may still be on their way
            deadline = time.monotonic() + FINAL_STATES_WAIT_S
            while not obs.has_final_states() and time.monotonic() < deadline:
                time.sleep(0.1)
    mapping_done.set()
    worker.join()  # maps the States still waiting (the final ones) before the recording closes
    rec.flush()
    rep = obs.report()
    for sink in obs.sinks:
        counts = sink.close()
        rep[sink.name] = {"path": str(sink.path), "messages": counts}
        log.info("%s %s: %d messages on %d topics", sink.name, sink.path, sum(counts.values()), len(counts))
    log.info("observer done: %d maps, %.3f s per map on average (max %.3f s), %d of %d States skipped",
             rep["maps"], rep["map_time_mean_s"], rep["map_time_max_s"], rep["states_skipped"], rep["states_received"])
    if cfg.run_dir is not None:
        atomic_write_text(cfg.run_dir / "observer.json", json.dumps(rep, indent=2) + "\n")
    rec.disconnect()
    return 0
