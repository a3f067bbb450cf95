"""The learner service: one robot's DiNNO training over Zenoh (the paper's Algorithm 1).

Run-book: ``swarmmap learner --robot I --config RUN_DIR/config.yaml``. Order of work:

1. subscribe to its training points (``robots/<I>/samples``), then announce itself
   (liveliness ``alive/learner/<I>``);
2. fetch the ground-truth validation set from the world (query ``world/map``);
3. collect points until its robot's traversal ends (offline training, as in the paper);
4. work out its neighbours (``learner.graph``), subscribe to their State and RoundComplete
   keys, announce ``alive/exchange/<I>``, wait for its neighbours' exchange tokens, then run
   Algorithm 1 for ``rounds`` rounds with
   DiNNO's node update, publishing ``Metrics`` every ``eval_every`` rounds;
5. write ``RUN_DIR/models/robot-<I>.pt``, its maps ``RUN_DIR/maps/robot-<I>.*`` (arrays, PNGs,
   a ROS map: :mod:`~swarmmap.services.learner.outputs`) and its training points
   ``RUN_DIR/data/robot-<I>.npz``, then publish its final ``Metrics``;
6. stay until the recorder says the run is over (``run/done``), then exit 0. The same message
   stops it at any point, e.g. when another learner failed.
"""

from __future__ import annotations

import io
import logging
import os
import threading
import time
from contextlib import nullcontext

import numpy as np
import torch

from swarmmap.services.learner.codec import StateCodec
from swarmmap.services.learner.dinno import DinnoNode, DsgdNode, DsgtNode, consensus_error, validation_bce, warm_up
from swarmmap.services.learner.exchange import (
    ExchangeStats,
    MemoryHub,
    MemoryTransport,
    PeerFailure,
    implausible,
    run_algorithm1,
    run_timed,
)
from swarmmap.services.learner.faults import FaultyTransport, any_faults
from swarmmap.services.learner.graphs import GraphError, dynamic_graph, metropolis_weights, run_graph
from swarmmap.services.learner.outputs import write_outputs
from swarmmap.services.learner.zenoh_transport import ZenohTransport
from swarmmap.shared.atomic import atomic_write_bytes
from swarmmap.shared.bus import Bus
from swarmmap.shared.compression import Compressor
from swarmmap.shared.config import RunConfig, task_robot
from swarmmap.shared.models import model_from_settings, pick_device, set_flat
from swarmmap.shared.protocol import (
    CHAINED_ENCODINGS,
    MAX_COVERAGE_BYTES,
    Keys,
    Metrics,
    Samples,
    WorldMap,
    all_finite,
    encode_state,
)
from swarmmap.shared.slots import ComputeSlots, slots_dir

log = logging.getLogger("learner")


def exchange_bytes(bus: Bus, robot: int) -> tuple[int, int]:
    """Bytes ``robot`` sent and received on Algorithm 1's keys (State and RoundComplete) over Zenoh."""
    own = (bus.keys.state(robot), bus.keys.round_complete(robot))

    def sent(key: str) -> bool:
        return key in own

    def received(key: str) -> bool:
        return key.endswith(("/state", "/round-complete")) and key not in own

    return bus.sent.bytes_where(sent), bus.received.bytes_where(received)


class Collector:
    """Buffers a robot's Samples until the one marked ``last``."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        self.done = threading.Event()
        self.first = threading.Event()
        self.refused = 0  # Samples after the one marked last
        self.position: tuple[float, float] | None = None  # where the robot was at its newest scan
        self._lock = threading.Lock()

    def add(self, msg: Samples) -> None:
        with self._lock:
            if self.done.is_set():  # the traversal is over: nothing may be added to it
                if self.refused == 0:
                    log.warning("refused Samples of robot %d after its last one (seq %d); further ones are only counted",
                                msg.sender, msg.seq)
                self.refused += 1
                return
            self.points.append(msg.points.numpy())
            self.labels.append(msg.labels.numpy())
            self.position = (float(msg.position[0]), float(msg.position[1]))
            if msg.last:
                self.done.set()
        self.first.set()

    def arrays(self, last_scans: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every point so far, or those of the ``last_scans`` most recent scans."""
        with self._lock:
            if not self.points:
                return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
            k = len(self.points) if last_scans is None else min(last_scans, len(self.points))
            return np.concatenate(self.points[-k:]), np.concatenate(self.labels[-k:])


class LearnerError(RuntimeError):
    """A learner cannot go on; ``status`` is the process exit status it asks for."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


class RobotLearner:
    """One robot's learner: its data, model, DinnoNode and metrics, on a shared Bus."""

    def __init__(self, cfg: RunConfig, robot: int, bus: Bus, device: torch.device):
        self.cfg, self.robot, self.bus, self.device = cfg, robot, bus, device
        self.s = cfg.learner
        self.candidates = set(range(cfg.robots)) - {robot}  # whoever the graph may make a neighbour
        self.neighbours: set[int] = set()
        self.collector = Collector()
        bus.subscribe(bus.keys.samples(robot), Samples, self.collector.add)
        self.metrics_pub = bus.publisher(bus.keys.metrics(robot))
        # Over Zenoh, Algorithm 1 publishes every State; in process, the States the metrics are
        # reported for are published too, so that an observer sees the maps form either way.
        self.state_pub = bus.publisher(bus.keys.state(robot)) if self.s.transport != "zenoh" else None
        self.stats = ExchangeStats()
        self.wire: MemoryTransport | None = None  # in process: its end of the hub, which counts the bytes
        self.compute_s = 0.0
        # Zenoh, one learner a process, by rounds: at most compute_slots of this host's learners train
        # at once (on a clock a learner never waits for its neighbours: it would keep its slot)
        self.slots: ComputeSlots | nullcontext = nullcontext()
        if self.s.compute_slots and self.s.transport == "zenoh" and not self.s.exchange_every_s:
            try:
                self.slots = ComputeSlots(slots_dir(cfg.run_id), self.s.compute_slots, home=robot)
            except OSError as exc:
                log.warning("robot %d: training without compute slots: %s", robot, exc)
        self.t_start = 0.0
        self.start_round = 0
        self.start_state: np.ndarray | None = None
        self.resumed = False
        self.latest: dict[int, np.ndarray] = {}  # on a clock: each neighbour's newest State
        self.final_state: np.ndarray | None = None
        self.before: dict[str, float] = {}  # counters of the runs this one resumes: metrics stay cumulative
        self.checkpoint_path = cfg.run_dir / "checkpoints" / f"robot-{robot}.pt" if cfg.run_dir is not None else None

    def resumable(self) -> dict | None:
        """This robot's checkpoint in the run directory, if there is one; one written with other
        settings is refused, never loaded."""
        if self.checkpoint_path is None or self.s.checkpoint_every == 0:
            return None
        for stale in self.checkpoint_path.parent.glob(f".robot-{self.robot}*.tmp"):
            stale.unlink(missing_ok=True)  # left by a learner killed while writing: the checkpoint itself is whole
        if not self.checkpoint_path.exists():
            return None
        try:
            doc = torch.load(self.checkpoint_path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a checkpoint we cannot read is not silently ignored
            raise LearnerError(f"robot {self.robot}: cannot read checkpoint {self.checkpoint_path}: {exc}", 2) from None
        mine, theirs = settings_fingerprint(self.cfg), doc.get("fingerprint")
        if theirs != mine:
            what = ("it comes from an older swarmmap" if theirs is None else
                    ", ".join(f"{k} {theirs.get(k)!r} there, {v!r} here" for k, v in mine.items() if theirs.get(k) != v))
            raise LearnerError(f"robot {self.robot}: refusing to resume from {self.checkpoint_path}: it was written by a run "
                               f"with other settings ({what}). Run into another --run-dir, or remove "
                               f"{self.checkpoint_path.parent} to start this one afresh", 2)
        return doc

    def counters(self) -> dict[str, float]:
        """This learner's counters, including those of the runs it resumed."""
        sent, received = self.wire.wire_bytes() if self.wire is not None else exchange_bytes(self.bus, self.robot)
        wall = time.monotonic() - self.t_start if self.t_start else 0.0
        now = {"bytes_sent": sent, "bytes_received": received, "compute_s": self.compute_s, "wait_s": self.stats.wait_s,
               "send_s": self.stats.send_s, "refused": self.refused(), "wall_time_s": wall}
        return {k: v + self.before.get(k, 0) for k, v in now.items()}

    @property
    def data_path(self):
        return self.checkpoint_path.with_name(f"robot-{self.robot}-data.pt")

    def save_checkpoint(self, k: int, theta: np.ndarray) -> None:
        """Atomically write what round ``k`` starts from. Offline, the training points do not
        change: they are written once, beside it, so that frequent checkpoints stay small."""
        doc = {"round": k, "state": torch.from_numpy(theta.copy()), "node": self.node.checkpoint(),
               "run_id": self.cfg.run_id, "fingerprint": settings_fingerprint(self.cfg), "counters": self.counters()}
        data = {"points": torch.from_numpy(self.points), "labels": torch.from_numpy(self.labels)}
        if self.s.data == "online":
            doc |= data
        elif k == 0 or not self.data_path.exists():
            buf = io.BytesIO()
            torch.save(data | {"fingerprint": settings_fingerprint(self.cfg)}, buf)
            atomic_write_bytes(self.data_path, buf.getvalue())
        buf = io.BytesIO()
        torch.save(doc, buf)
        atomic_write_bytes(self.checkpoint_path, buf.getvalue())

    def load_data(self, doc: dict) -> None:
        if "points" not in doc:
            try:
                doc = torch.load(self.data_path, map_location="cpu", weights_only=True)
            except Exception as exc:
                raise LearnerError(f"robot {self.robot}: cannot read its training points {self.data_path}: {exc}", 2) from None
        self.points, self.labels = doc["points"].numpy(), doc["labels"].numpy()

    def prepare(self, world: WorldMap, stop: threading.Event) -> None:
        """Wait for the end of the traversal (or resume from a checkpoint), then build the node."""
        s, robot = self.s, self.robot
        doc = self.resumable()
        if doc is not None:
            self.load_data(doc)
            self.setup(world)
            self.node.restore(doc["node"])
            self.start_round, self.start_state = int(doc["round"]), doc["state"].numpy()
            set_flat(self.node.model, torch.from_numpy(self.node.params_of(self.start_state).copy()))
            self.resumed, self.before = True, dict(doc.get("counters", {}))
            log.info("robot %d: resuming from %s at round %d", robot, self.checkpoint_path, self.start_round)
            return
        ready = self.collector.first if s.data == "online" else self.collector.done
        deadline = time.monotonic() + s.collect_timeout_s
        while not ready.is_set() and not stop.is_set() and time.monotonic() < deadline:
            ready.wait(0.1)  # a stop (Ctrl-C, the run's end) is heard at once
        if not (ready.is_set() or stop.is_set()):
            what = "no Samples" if s.data == "online" else "no Samples with last=true"
            raise LearnerError(f"robot {robot}: {what} on {self.bus.keys.samples(robot)} within {s.collect_timeout_s:.0f} s", 3)
        if stop.is_set():
            raise InterruptedError
        self.points, self.labels = self.collector.arrays(s.window_scans if s.data == "online" else None)
        if len(self.points) == 0:
            raise LearnerError(f"robot {robot}: the traversal ended without a single training point", 3)
        log.info("robot %d: %d training points (%.1f%% occupied)", robot, len(self.points), 100 * self.labels.mean())
        self.setup(world)
        if self.checkpoint_path is not None and s.checkpoint_every:  # a learner restarted from now on keeps its data
            self.save_checkpoint(0, self.node.state())

    def setup(self, world: WorldMap) -> None:
        """The validation set, the graph and the node, once the points are known."""
        s, robot = self.s, self.robot
        self.world = world
        self.val_x = torch.from_numpy(world.val_points.numpy().copy()).to(self.device)
        self.val_y = torch.from_numpy(world.val_labels.numpy().copy()).to(self.device)
        positions = world.positions.numpy() if world.positions is not None else None
        try:
            graph = run_graph(s, self.cfg.robots, positions)
        except GraphError as exc:
            raise LearnerError(str(exc), 2) from None
        self.neighbours = graph[robot]
        self.build_node(graph)

    def build_node(self, graph: dict[int, set[int]]) -> None:
        """The node of ``learner.algorithm`` on this robot's points."""
        s, robot = self.s, self.robot
        model = model_from_settings(s, self.world.bounds, self.cfg.seed).to(self.device)
        data = (torch.from_numpy(self.points.copy()), torch.from_numpy(self.labels.copy()))
        seed = self.cfg.seed * 1000 + robot + 1
        bounds = self.world.bounds
        if s.algorithm == "dsgd":
            self.node = DsgdNode(model, *data, s, seed, metropolis_weights(graph, robot), robot, bounds)
        elif s.algorithm == "dsgt":
            self.node = DsgtNode(model, *data, s, seed, metropolis_weights(graph, robot), robot, bounds)
        else:
            self.node = DinnoNode(model, *data, s, seed, bounds)
        if self.node.coverage is not None:
            c = self.node.coverage
            log.info("robot %d: noise-contrastive prior on %.0f%% of the map (cells of %.2f m farther than %.2f m "
                     "from its data)", robot, 100 * c.uncovered_fraction(), c.cell, c.margin)

    def publish_metrics(self, k: int, theta: np.ndarray, peers: dict[int, np.ndarray], final: bool = False) -> Metrics:
        c, params_of = self.counters(), self.node.params_of
        msg = Metrics(run=self.cfg.run_id, sender=self.robot, round=k, wall_time_s=c["wall_time_s"],
                      val_bce=validation_bce(self.node.model, self.val_x, self.val_y),
                      consensus_error=consensus_error(params_of(theta), {j: params_of(p) for j, p in peers.items()}),
                      bytes_sent=int(c["bytes_sent"]), bytes_received=int(c["bytes_received"]),
                      compute_s=c["compute_s"], wait_s=c["wait_s"], send_s=c["send_s"],
                      n_points=len(self.points), pid=os.getpid(), refused=int(c["refused"]), final=final)
        self.metrics_pub.put(msg)
        if self.state_pub is not None:
            self.state_pub.put_bytes(encode_state(self.cfg.run_id, self.robot, k, theta))
        return msg

    def refused(self) -> int:
        """Messages this learner refused: malformed or foreign ones (its bus), implausible or
        far-future States, Samples after the last."""
        wire = sum(self.wire.refused.values()) if self.wire is not None else 0
        return sum(self.bus.dropped.values()) + sum(self.stats.refused.values()) + self.collector.refused + wire

    def check_state(self, theirs: np.ndarray, own: np.ndarray | None) -> str | None:
        if theirs.size != self.node.state_size():
            return f"{theirs.size} values, this node's State has {self.node.state_size()}"
        params_of = self.node.params_of  # DSGT's State also carries its gradient tracker: judge the parameters
        return implausible(params_of(theirs), None if own is None else params_of(own), self.s.max_state_distance)

    def node_update(self, c: int, theta: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
        """Algorithm 1's round ``c``: training rounds c E .. c E + E - 1 (E = exchange_every), the
        first with the neighbours' States of this exchange, the others against them as they were."""
        e = self.s.exchange_every
        with self.slots:  # (its neighbours' next States cannot come before it sends its own: it waits without one)
            self.checkpoint_if_due(c, theta)
            for k in range(c * e, (c + 1) * e):
                theta = self.train_round(k, theta, peers, exchange=k == c * e)
        return theta

    def timed_update(self, k: int, theta: np.ndarray, fresh: dict[int, np.ndarray]) -> np.ndarray:
        """Training round ``k`` on a clock (``exchange_every_s``): an exchange round for the
        neighbours whose States came since the last round, if any."""
        self.latest.update(fresh)
        self.checkpoint_if_due(k, theta)  # (on a clock exchange_every is 1: Algorithm 1's rounds are training rounds)
        return self.train_round(k, theta, self.latest, exchange=bool(fresh), fresh=fresh)

    def checkpoint_if_due(self, c: int, theta: np.ndarray) -> None:
        """What Algorithm 1's round ``c`` starts from, when its training rounds c E .. c E + E - 1
        pass a multiple of ``checkpoint_every`` (not in the round this learner resumed from: that
        one is on disk)."""
        every, e = self.s.checkpoint_every, self.s.exchange_every
        if every and (c * e) % every < e and c != self.start_round and self.checkpoint_path is not None:
            self.save_checkpoint(c, theta)

    def forget(self, j: int) -> None:
        """Neighbour ``j`` went silent (on a clock): the update stops pulling towards its last State."""
        self.latest.pop(j, None)
        self.node.forget(j)  # (a DinnoNode: a clock needs algorithm dinno)

    def train_round(self, k: int, theta: np.ndarray, peers: dict[int, np.ndarray], exchange: bool,
                    fresh: dict[int, np.ndarray] | None = None) -> np.ndarray:
        """Training round ``k``: the round's metrics every ``eval_every`` rounds (consensus error
        against ``peers``), then the node's update, with the neighbours' States that came
        (``fresh``, default ``peers``) where ``exchange``, else against the States it holds."""
        s = self.s
        if s.data == "online":  # DiNNO's sliding window over the scans received so far
            self.points, self.labels = self.collector.arrays(s.window_scans)
            self.node.set_data(self.points, self.labels)
        if k % s.eval_every == 0:
            m = self.publish_metrics(k, theta, peers)
            log.info("robot %d round %d: val_bce %.4f consensus %.4f", self.robot, k, m.val_bce, m.consensus_error)
        t0 = time.perf_counter()
        theta = self.node.update(k, theta, peers if fresh is None else fresh) if exchange else self.node.local_update(k, theta)
        self.compute_s += time.perf_counter() - t0
        if not all_finite(self.node.params_of(theta)):
            raise LearnerError(f"robot {self.robot}: training diverged in round {k}: its parameters are no longer "
                               f"finite (settings too aggressive for this plan: lr_start {s.lr_start:g}, rho_init "
                               f"{s.rho_init:g}, consensus {s.consensus})", 6)
        return theta

    def train(self, transport, stop: threading.Event) -> None:
        """Algorithm 1 for ``rounds`` rounds over ``transport``, then the final metrics and outputs."""
        s, robot = self.s, self.robot
        self.t_start = time.monotonic()
        try:
            start = self.node.state() if self.start_state is None else self.start_state
            if s.exchange_every_s > 0:
                final = run_timed(robot, self.neighbours, s.rounds, start, self.timed_update, transport, s.exchange_every_s,
                                  start_round=self.start_round, stats=self.stats, stop=stop, check_state=self.check_state,
                                  silent_after=s.silent_after_s, forget=self.forget)
            else:
                final = run_algorithm1(robot, self.neighbours, s.rounds // s.exchange_every, start, self.node_update,
                                       transport, start_round=self.start_round, stats=self.stats, stop=stop,
                                       peer_timeout=s.peer_timeout_s, resend_after=s.resend_after_s,
                                       check_state=self.check_state, silent_after=s.silent_after_s,
                                       rejoin=self.node.rejoin, resumed=self.resumed, rejoin_wait=s.rejoin_wait_s,
                                       keep_rounds=-(-s.checkpoint_every // s.exchange_every) + 2,
                                       round_wait=s.round_wait_s)
        except PeerFailure as exc:
            raise LearnerError(str(exc), 5) from None
        ignored, unusable = getattr(transport, "ignored", 0), getattr(transport, "unusable", 0)  # (a StateCodec's)
        if self.stats.missed or ignored or unusable:
            log.info("robot %d: rounds went on without %d neighbour State(s) that did not come in time; %d message(s) "
                     "from neighbours out of range ignored; %d State(s) that could not be rebuilt", robot,
                     self.stats.missed, ignored, unusable)
        set_flat(self.node.model, torch.from_numpy(self.node.params_of(final).copy()))
        self.final_state = final
        self.finish(final, self.stats.final_peers)

    def finish(self, final: np.ndarray, peers: dict[int, np.ndarray]) -> None:
        """The final metrics and outputs."""
        s, robot = self.s, self.robot
        if self.cfg.run_dir is not None:  # before the final Metrics: a run is over only once every map is on disk
            write_outputs(self.cfg, robot, self.node.model, self.world, self.points, self.labels)
        m = self.publish_metrics(s.rounds, final, peers, final=True)
        log.info("robot %d done: %d rounds in %.1f s, val_bce %.4f (compute %.1f s, waiting %.1f s, sending %.1f s)",
                 robot, s.rounds, m.wall_time_s, m.val_bce, m.compute_s, m.wait_s, m.send_s)
        if isinstance(self.slots, ComputeSlots):
            log.info("robot %d: %.1f s of its rounds waiting for one of this host's %d compute slots", robot,
                     self.slots.wait_s, s.compute_slots)
        if self.node.coverage is not None:
            log.info("robot %d: %.0f%% of the map was away from every robot's data it heard of (%.0f%% from its own)",
                     robot, 100 * self.node.coverage.uncovered_fraction(), 100 * (1 - self.node.coverage.own.mean()))


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The learner's main work; returns the process exit status.

    With ``learner.transport`` zenoh the process serves robot ``learner.robot``; with inproc it
    serves every robot of the run, each node in a thread of its own, exchanging State and
    RoundComplete through memory (DiNNO's single-process setting) while data and metrics still
    travel over Zenoh."""
    s = cfg.learner
    inproc = s.transport == "inproc"
    if inproc:
        robots = list(range(cfg.robots))
    else:
        robots = [task_robot(s.robot, cfg.robots, "learner.robot")]
    torch.set_num_threads(s.torch_threads)
    device = pick_device(s.device)
    keys = Keys(cfg.key_prefix, cfg.run_id)
    with Bus.open(cfg.zenoh, keys, "learner", robots[0]) as bus:
        bus.end_with_run(stop)
        learners = [RobotLearner(cfg, r, bus, device) for r in robots]
        for r in robots:
            bus.announce(r)
        warm_up(s.optimizer)  # while the world starts and the robots drive
        world = bus.query(keys.world_map(), WorldMap, timeout=s.collect_timeout_s, stop=stop)
        if world is None:
            if stop.is_set():
                return 0
            log.error("no reply from the world on %s within %.0f s", keys.world_map(), s.collect_timeout_s)
            return 3
        log.info("robots %s (%s transport): model %s %s on %s", robots, s.transport, s.model, s.model_shape, device)
        try:
            for learner in learners:
                learner.prepare(world, stop)
            if s.algorithm == "centralized":
                train_centralized(learners, stop)
            elif inproc:
                hub = MemoryHub({r.robot: r.neighbours for r in learners}, run=cfg.run_id)  # through the wire codec
                for r in learners:
                    r.wire = hub.transport(r.robot)
                run_all(learners, {r.robot: links(r.wire, r) for r in learners}, stop)
            else:
                # Subscribe to exactly its neighbours (known once the world answered), then
                # say so with an "exchange" token; neighbours start Algorithm 1 once they see it.
                me = learners[0]
                transport = ZenohTransport(bus, me.robot, me.neighbours, me.node.state_size(), s.inbox_limit)
                me.node.new_state = transport.new_state  # States written straight into their payloads
                if any_faults(cfg.faults):
                    log.warning("robot %d: injecting faults on its incoming links: %s", me.robot, cfg.faults.model_dump())
                transport = links(transport, me)
                bus.announce(me.robot, service="exchange")
                missing = bus.wait_alive("exchange", {str(j) for j in me.neighbours}, s.peer_timeout_s, stop)
                if me.neighbours and missing == {str(j) for j in me.neighbours} and not stop.is_set():
                    raise LearnerError(f"neighbour learner(s) {sorted(missing)} never became ready to exchange", 4)
                if missing:
                    log.warning("robot %d: starting without neighbour(s) %s (not ready to exchange)", me.robot, sorted(missing))
                run_all(learners, {me.robot: transport}, stop)
                # Until the run is over, say the final State again now and then: a neighbour
                # that restarts behind a finished team catches up to it.
                deadline = time.monotonic() + (s.peer_timeout_s if bus.alive("recorder") else 0.5)
                while not stop.wait(min(s.resend_after_s, max(0.0, deadline - time.monotonic()))) and time.monotonic() < deadline:
                    transport.send_state(s.rounds // s.exchange_every, me.final_state)
        except LearnerError as exc:
            log.error("%s", exc)
            return exc.status
        except InterruptedError:
            log.info("robots %s: stopped", robots)
            return 0
        # Stay until the run is over (the recorder's run/done): a launcher that stops everything
        # once one service exits (compose's --exit-code-from) must not cut the others short.
        # Without a recorder, stay until every neighbour has its final State from us.
        if inproc or s.algorithm == "centralized":
            stop.wait(s.peer_timeout_s if bus.alive("recorder") else 0.5)
    return 0


def links(transport, learner: RobotLearner) -> StateCodec:
    """A node's links as its settings ask: faults injected where the run's ``faults`` say, States
    encoded (``learner.compression``) and numbered by training round (``learner.exchange_every``),
    and on a dynamic disk graph limited to the neighbours within ``comm_radius_m``."""
    cfg, robot, s = learner.cfg, learner.robot, learner.s
    if any_faults(cfg.faults):
        transport = FaultyTransport(transport, robot, cfg.faults)
    dynamic = dynamic_graph(s)
    compressor = Compressor(s.compression, s.topk_density, s.keyframe_every, s.quant_bits, s.lowrank_rank,
                            weight_matrices(learner.node.model))
    if s.compression in CHAINED_ENCODINGS:
        learner.node.public = lambda: compressor.replica  # the consensus terms use what the neighbours hold of it
    coverage = learner.node.coverage if s.share_coverage else None
    if coverage is not None and (coverage.cells + 7) // 8 > MAX_COVERAGE_BYTES:
        log.warning("robot %d: coverage not shared: %d cells of %.2f m are more than a State may carry (%d bytes); "
                    "raise learner.unseen_margin_m to share it", robot, coverage.cells, coverage.cell, MAX_COVERAGE_BYTES)
        coverage = None
    return StateCodec(transport, robot, compressor, s.exchange_every, radius=s.comm_radius_m if dynamic else None,
                      position=(lambda: learner.collector.position) if dynamic else None, coverage=coverage)


def weight_matrices(model: torch.nn.Module) -> list[tuple[int, int, int]]:
    """(offset, rows, cols) of each 2-D parameter in the flat parameter vector (lowrank States)."""
    out, at = [], 0
    for p in model.parameters():
        if p.dim() == 2:
            out.append((at, int(p.shape[0]), int(p.shape[1])))
        at += p.numel()
    return out


def train_centralized(learners: list[RobotLearner], stop: threading.Event) -> None:
    """The centralized baseline: one model trained on every robot's points, reported as every
    robot's model."""
    head = learners[0]
    head.points = np.concatenate([r.points for r in learners])
    head.labels = np.concatenate([r.labels for r in learners])
    head.build_node({head.robot: set()})
    log.info("centralized: one model on %d points of %d robots", len(head.points), len(learners))
    head.train(MemoryHub({head.robot: set()}).transport(head.robot), stop)
    final = head.node.state()
    for r in learners[1:]:
        r.node, r.points, r.t_start, r.compute_s = head.node, head.points, head.t_start, head.compute_s
        r.finish(final, {})


def settings_fingerprint(cfg: RunConfig) -> dict:
    """What a checkpoint must share with the run that resumes from it."""
    s = cfg.learner
    return {"checkpoint_format": 2, "seed": cfg.seed, "robots": cfg.robots, "model": s.model,
            "model_shape": list(s.model_shape), "algorithm": s.algorithm,
            "regularization": s.regularization if s.model == "bnn" else None, "data": s.data,
            "consensus": s.consensus, "exchange_every": s.exchange_every,
            "floorplan": cfg.world.floorplan, "waypoints": cfg.world.waypoints}


def run_all(learners: list[RobotLearner], transports: dict, stop: threading.Event) -> None:
    """Train every learner, each in a thread of its own when there are several."""
    if len(learners) == 1:
        learners[0].train(transports[learners[0].robot], stop)
        return
    errors: list[BaseException] = []

    def train(learner: RobotLearner) -> None:
        try:
            learner.train(transports[learner.robot], stop)
        except BaseException as exc:  # re-raised in the caller's thread
            errors.append(exc)
            stop.set()

    threads = [threading.Thread(target=train, args=(r,), name=f"robot-{r.robot}") for r in learners]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
