"""The learner service: one robot's DiNNO training over Zenoh (the paper's Algorithm 1).

Run-book: ``swarmmap learner --robot I --config RUN_DIR/config.yaml``. Order of work:

1. subscribe to its training points (``robots/<I>/samples``), then announce itself
   (liveliness ``alive/learner/<I>``);
2. fetch the ground-truth validation set from the world (query ``world/map``);
3. collect points until its robot's traversal ends (offline training, as in the paper), or
   resume from its checkpoint;
4. work out its neighbours (``learner.graph``), subscribe to their State and RoundComplete
   keys, announce ``alive/exchange/<I>``, wait for its neighbours' exchange tokens, then run
   Algorithm 1 for ``rounds`` rounds with
   DiNNO's node update, publishing ``Metrics`` every ``eval_every`` rounds;
5. write ``RUN_DIR/models/robot-<I>.pt``, its maps ``RUN_DIR/maps/robot-<I>.*`` (arrays, PNGs,
   a ROS map: :mod:`~swarmmap.services.learner.outputs`) and its training points
   ``RUN_DIR/data/robot-<I>.npz``, then publish its final ``Metrics``;
6. stay until the recorder says the run is over (``run/done``), then exit 0. The same message
   stops it at any point, e.g. when another learner failed.

This module only composes the parts: the node from the registry
(:mod:`~swarmmap.services.learner.registry`), its links (a Zenoh or in-memory link, faults
where asked, the State codec), Algorithm 1 or the clock mode, the sub-round schedule, checkpoints
and outputs. With ``learner.transport`` inproc one process serves every robot, each node in a
thread of its own, exchanging through memory (DiNNO's single-process setting) while data and
metrics still travel over Zenoh.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch

from swarmmap.services.learner.algorithm1 import Algorithm1, RoundLoop
from swarmmap.services.learner.attacks import HostileTransport, flood_metrics
from swarmmap.services.learner.centralized import train_centralized
from swarmmap.services.learner.checkpoints import Checkpoints
from swarmmap.services.learner.clock import ClockExchange
from swarmmap.services.learner.codec import StateCodec
from swarmmap.services.learner.collector import Collector
from swarmmap.services.learner.errors import LearnerError
from swarmmap.services.learner.exchange import CHECK_EVERY_S, ExchangeStats, PeerFailure
from swarmmap.services.learner.faults import FaultyTransport, any_faults
from swarmmap.services.learner.fitting import fit
from swarmmap.services.learner.membership import Replay
from swarmmap.services.learner.memory_link import MemoryLink
from swarmmap.services.learner.metrics import consensus_error, validation_bce
from swarmmap.services.learner.node import warm_up
from swarmmap.services.learner.outputs import write_outputs
from swarmmap.services.learner.pace import Pace
from swarmmap.services.learner.registry import RuleChoice, make_node, node_inputs
from swarmmap.services.learner.robust import RoundScreen
from swarmmap.services.learner.screening import GROUP_FACTOR, StateScreen
from swarmmap.services.learner.settings import ScheduleSettings, exchange_rules
from swarmmap.services.learner.subrounds import SubRounds
from swarmmap.services.learner.transport import Link, MemoryHub, Transport
from swarmmap.services.learner.zenoh_transport import ZenohTransport
from swarmmap.shared.learning.graphs import GraphError, run_graph
from swarmmap.shared.learning.layout import StateLayout
from swarmmap.shared.learning.models import pick_device, set_flat
from swarmmap.shared.learning.networks import build_network
from swarmmap.shared.plugins import origin
from swarmmap.shared.run.config import RunConfig, task_robot
from swarmmap.shared.run.fingerprint import settings_fingerprint
from swarmmap.shared.run.sections import LearnerSettings, part_options
from swarmmap.shared.run.slots import ComputeSlots, slots_dir
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.codec import encode_state
from swarmmap.shared.wire.compression import Encoder
from swarmmap.shared.wire.compression import compressor as make_compressor
from swarmmap.shared.wire.protocol import MAX_COVERAGE_BYTES, Keys, Metrics, Samples, WorldMap
from swarmmap.shared.world.unseen import Coverage

if TYPE_CHECKING:
    from swarmmap.services.learner.explorer import Explorer

log = logging.getLogger("learner")
MakeLink = Callable[[StateLayout], Link]


class RobotLearner:
    """One robot's learner: its data, node, links and metrics, on a shared Bus."""

    def __init__(self, cfg: RunConfig, robot: int, bus: Bus, device: torch.device):
        self.cfg, self.robot, self.bus, self.device = cfg, robot, bus, device
        self.s = s = cfg.learner
        self.online = s.data == "online" or cfg.explore.active  # (an exploring robot's learner trains while it drives)
        self.collector = Collector(s.window_scans if self.online else None)  # online: the window only
        bus.subscribe(bus.keys.samples(robot), Samples, self.collector.add)
        self.metrics_pub = bus.publisher(bus.keys.metrics(robot))
        # Over Zenoh, Algorithm 1 publishes every State; in process, the States the metrics are
        # reported for are published too, so that an observer sees the maps form either way.
        self.state_pub = bus.publisher(bus.keys.state(robot)) if s.transport != "zenoh" else None
        self.stats = ExchangeStats()
        self.wire: MemoryLink | None = None  # in process: its end of the hub, which counts the bytes
        self.codec: StateCodec | None = None
        self.replay: Replay | None = None  # Algorithm 1's own States of its last rounds, for neighbours that replay them
        self.slots = compute_slots(cfg, robot)
        self.rounds: SubRounds | None = None
        self.t_start = 0.0
        self.start_round, self.start_state, self.resumed, self.doc = 0, None, False, None
        self.before: dict[str, float] = {}  # counters of the runs this one resumes: metrics stay cumulative
        self.explorer: Explorer | None = None  # (imported where a robot explores: its grids need scipy)
        self.checkpoints = (Checkpoints(cfg.run_dir / "checkpoints", robot, cfg.run_id, settings_fingerprint(cfg), self.online)
                            if cfg.run_dir is not None and s.checkpoint_every else None)

    def listen(self, world: WorldMap, stop: threading.Event) -> None:
        """Its graph and, exploring, its subscriptions to its team's goals and scans, said with its
        "explore" token (the world drives once every robot's learner has one)."""
        self.world, self.stop = world, stop
        positions = world.positions.numpy() if world.positions is not None else None
        try:
            self.graph = run_graph(self.cfg.graph(), self.cfg.robots, positions)
        except GraphError as exc:
            raise LearnerError(str(exc), 2) from None
        self.neighbours = self.graph[self.robot]
        if self.cfg.explore.active:
            from swarmmap.services.learner.explorer import Explorer

            self.explorer = Explorer(self.cfg, self.robot, self.bus, self.collector, self.neighbours, lambda: self.node, world)
            self.bus.announce(self.robot, service="explore")

    def prepare(self, stop: threading.Event) -> None:
        """Its training points (the traversal's, or a checkpoint's) and the validation set."""
        world = self.world
        self.val_x = torch.from_numpy(world.val_points.numpy().copy()).to(self.device)
        self.val_y = torch.from_numpy(world.val_labels.numpy().copy()).to(self.device)
        self.doc = self.checkpoints.resumable() if self.checkpoints is not None else None
        if self.doc is not None and self.explorer is not None:
            raise LearnerError(f"robot {self.robot}: an exploring learner cannot take up its robot's drive from "
                               f"{self.checkpoints.path} (the scans of the legs driven are gone): the run stops", 2)
        if self.doc is not None:
            self.points, self.labels = self.checkpoints.points(self.doc)
            return
        self.points, self.labels = self.collector.wait(self.s, self.bus.keys.samples(self.robot), stop, f"robot {self.robot}",
                                                       online=self.online, through_leg=0 if self.explorer else None)
        log.info("robot %d: %d training points (%.1f%% occupied)", self.robot, len(self.points), 100 * self.labels.mean())

    def window(self, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Online, round ``k``'s points: the newest ``window_scans`` scans' (DiNNO's sliding window),
        or, exploring, those of the legs driven so far where they change (None: unchanged)."""
        data = self.explorer.window(k, self.stop) if self.explorer is not None else self.collector.arrays(self.s.window_scans)
        if data is not None:
            self.points, self.labels = data
        return data

    def compose(self, make_link: MakeLink | None, resume: bool = True) -> Transport | None:
        """Build the node of ``learner.algorithm`` on this robot's points, its links over
        ``make_link(layout)`` (None: none) and its round schedule; ``resume`` it from its
        checkpoint, or write round 0's."""
        s, cfg = self.s, self.cfg
        model = build_network(cfg.network(), self.world.bounds, cfg.seed).to(self.device)
        inputs = node_inputs(s, model, self.points.copy(), self.labels.copy(), cfg.seed * 1000 + self.robot + 1, self.world.bounds)
        transport, public = None, None
        if make_link is not None:
            compressor = state_compressor(s, s.compression, s.compression_options, list(inputs.layout.matrices))
            transport = self.codec = state_links(self, make_link(inputs.layout), compressor, inputs.coverage)
            transport = hostile(cfg, self.robot, transport, inputs.layout, self.metrics_pub.put)
            inputs = dataclasses.replace(inputs, new_state=transport.new_state)  # States written straight into their payloads
            public = partial(public_state, self.codec)  # (the consensus terms use what the neighbours hold)
        self.node = make_node(s.algorithm, inputs, RuleChoice.of(s, self.graph, self.robot, public))
        if (c := inputs.coverage) is not None:
            log.info("robot %d: noise-contrastive prior on %.0f%% of the map (cells of %.2f m farther than %.2f m from its "
                     "data)", self.robot, 100 * c.uncovered_fraction(), c.cell, c.margin)
        if resume:
            resume_node(self)
        self.rounds = SubRounds(self.node, ScheduleSettings.of(s), self.report, save=self.save if self.checkpoints else None,
                                window=self.window if self.online else None, start_round=self.start_round,
                                slots=self.slots, name=f"robot {self.robot}",
                                diverged=f"settings too aggressive for this plan: lr_start {s.lr_start:g}, rho_init "
                                         f"{s.rho_init:g}, consensus {s.consensus}")
        return transport

    def save(self, c: int, theta: np.ndarray) -> None:
        self.checkpoints.save(c, theta, self.node.checkpoint(), self.counters(), self.points, self.labels)

    def counters(self) -> dict[str, float]:
        """This learner's counters, including those of the runs it resumed."""
        sent, received = self.wire.wire_bytes() if self.wire is not None else exchange_bytes(self.bus, self.robot)
        wall = time.monotonic() - self.t_start if self.t_start else 0.0
        compute = self.rounds.compute_s if self.rounds is not None else 0.0
        # refused: malformed or foreign messages (its bus, its in-memory link), implausible or far-future States, late Samples
        refused = (sum(self.bus.dropped.values()) + sum(self.stats.refused.values()) + self.collector.refused
                   + (sum(self.wire.refused.values()) if self.wire is not None else 0))
        now = {"bytes_sent": sent, "bytes_received": received, "compute_s": compute, "wait_s": self.stats.wait_s,
               "send_s": self.stats.send_s, "refused": refused, "wall_time_s": wall}
        return {k: v + self.before.get(k, 0) for k, v in now.items()}

    def report(self, k: int, theta: np.ndarray, peers: dict[int, np.ndarray]) -> None:
        """Round ``k``'s Metrics, published."""
        msg = self.publish(self.metrics(k, theta, peers), theta)
        log.info("robot %d round %d: val_bce %.4f consensus %.4f", self.robot, k, msg.val_bce, msg.consensus_error)

    def metrics(self, k: int, theta: np.ndarray, peers: dict[int, np.ndarray], final: bool = False) -> Metrics:
        """Round ``k``'s Metrics: the validation loss, the consensus error against ``peers``, the counters."""
        c, params_of = self.counters(), self.node.layout.params_of
        return Metrics(run=self.cfg.run_id, sender=self.robot, round=k, wall_time_s=c["wall_time_s"],
                       val_bce=validation_bce(self.node.model, self.val_x, self.val_y),
                       consensus_error=consensus_error(params_of(theta), {j: params_of(p) for j, p in peers.items()}),
                       bytes_sent=int(c["bytes_sent"]), bytes_received=int(c["bytes_received"]),
                       compute_s=c["compute_s"], wait_s=c["wait_s"], send_s=c["send_s"],
                       n_points=len(self.points), pid=os.getpid(), refused=int(c["refused"]), final=final,
                       repeated_samples=self.collector.repeated, refused_from=refused_from(self.stats, self.bus))

    def publish(self, msg: Metrics, theta: np.ndarray) -> Metrics:
        """Publish ``msg`` (and, in process, the State it was taken of, for the observer)."""
        self.metrics_pub.put(msg)
        if self.state_pub is not None:
            self.state_pub.put_bytes(encode_state(self.cfg.run_id, self.robot, msg.round, theta))
        return msg

    def train(self, transport: Transport, stop: threading.Event) -> None:
        """Algorithm 1 (or the clock mode) for ``rounds`` rounds over ``transport``, then the final metrics and outputs."""
        self.t_start = time.monotonic()
        try:
            final = exchange(self, transport, stop)
        except PeerFailure as exc:
            raise LearnerError(str(exc), 5) from None
        set_flat(self.node.model, torch.from_numpy(self.node.layout.params_of(final).copy()))
        self.final_state = final
        self.finish(final, self.stats.final_peers)

    def finish(self, final: np.ndarray, peers: dict[int, np.ndarray]) -> None:
        """The final metrics and outputs."""
        s, robot = self.s, self.robot
        msg = self.metrics(s.rounds, final, peers, final=True)  # (its times are the training's)
        if self.cfg.run_dir is not None:  # before the final Metrics: a run is over only once every map is on disk
            write_outputs(self.cfg, robot, self.node.model, self.world, self.points, self.labels)
        self.final_metrics = self.publish(msg, final)
        log_finished(self)


def resume_node(learner: RobotLearner) -> None:
    """A learner's node from the checkpoint found by :meth:`RobotLearner.prepare`, if any; else round 0's written."""
    if learner.doc is None:
        if learner.checkpoints is not None:  # a learner restarted from now on keeps its data
            learner.save(0, learner.node.state())
        return
    learner.node.restore(learner.doc["node"])
    learner.start_round, learner.start_state = int(learner.doc["round"]), learner.doc["state"].numpy()
    set_flat(learner.node.model, torch.from_numpy(learner.node.layout.params_of(learner.start_state).copy()))
    learner.resumed, learner.before = True, dict(learner.doc.get("counters", {}))
    log.info("robot %d: resuming from %s at round %d", learner.robot, learner.checkpoints.path, learner.start_round)


def log_finished(learner: RobotLearner) -> None:
    """What a finished learner says of its run: time, loss, where the time went, what its prior covered."""
    s, robot, m, node = learner.s, learner.robot, learner.final_metrics, learner.node
    log.info("robot %d done: %d rounds in %.1f s, val_bce %.4f (compute %.1f s, waiting %.1f s, sending %.1f s)",
             robot, s.rounds, m.wall_time_s, m.val_bce, m.compute_s, m.wait_s, m.send_s)
    if isinstance(learner.slots, ComputeSlots):
        log.info("robot %d: %.1f s of its rounds waiting for one of this host's %d compute slots", robot,
                 learner.slots.wait_s, s.compute_slots)
    if node.coverage is not None:
        log.info("robot %d: %.0f%% of the map was away from every robot's data it heard of (%.0f%% from its own)",
                 robot, 100 * node.coverage.uncovered_fraction(), 100 * (1 - node.coverage.own.mean()))
    if (ex := learner.explorer) is not None:
        log.info("robot %d: %.1f s choosing its goals, %.1f s waiting for its robot's legs", robot, ex.choose_s, ex.waited_s)


def exchange(learner: RobotLearner, transport: Transport, stop: threading.Event) -> np.ndarray:
    """A learner's rounds over ``transport``: Algorithm 1, or on a clock (``exchange_every_s``); the final State."""
    s, node, rounds = learner.s, learner.node, learner.rounds
    start = node.state() if learner.start_state is None else learner.start_state
    rules, screen = exchange_rules(s), StateScreen(node.layout, s.max_state_distance)
    stale = StateScreen(node.layout, GROUP_FACTOR * s.max_state_distance, norms=False)  # against own parameters rounds old
    # (on a dynamic disk graph two subteams that meet differ by what each learnt apart: bounds, not the screen)
    round_screen = RoundScreen(node.layout, s.robust_spread_factor) if s.robust and not learner.cfg.graph().dynamic else None
    if s.exchange_every_s > 0:
        final = ClockExchange(learner.robot, learner.neighbours, rounds.clock_update, transport, s.exchange_every_s, rules,
                              check=screen, check_stale=stale, forget=rounds.forget, stats=learner.stats, stop=stop
                              ).run(start, s.rounds, learner.start_round)
    else:
        machine = Algorithm1(learner.robot, learner.neighbours, rounds.exchange_update, transport, rules, check=screen,
                             screen=round_screen, check_stale=stale, rejoin=node.rejoin, stats=learner.stats, stop=stop)
        pace = Pace(learner.robot, slow_link(learner))
        final = RoundLoop(machine, pace).run(start, s.rounds // s.exchange_every, learner.start_round, learner.resumed)
        learner.replay = machine.replay  # (a finished learner answers a neighbour that restarted behind it)
    codec, stats = learner.codec, learner.stats
    if codec is not None and (stats.missed or codec.ignored or codec.unusable):
        log.info("robot %d: rounds went on without %d neighbour State(s) that did not come in time; %d message(s) "
                 "from neighbours out of range ignored; %d State(s) that could not be rebuilt", learner.robot,
                 stats.missed, codec.ignored, codec.unusable)
    return final


def state_compressor(s: LearnerSettings, name: str, options: dict, matrices: list[tuple[int, int, int]]) -> Encoder:
    """The encoder of the compression plug-in ``name`` with the learner's knobs and its own ``options``."""
    return make_compressor(name, s.topk_density, s.keyframe_every, s.quant_bits, s.lowrank_rank, matrices,
                           part_options("compressions", "compression", name, options))


def public_state(codec: StateCodec) -> np.ndarray | None:
    """What the neighbours hold of a node's State: its chain's replica where its States are chained
    (the encoding may change during a run: a slow link), else None (its own parameters)."""
    return codec.compressor.replica


def slow_link(learner: RobotLearner) -> Callable[[], str] | None:
    """What a learner whose links set the pace does (:mod:`~swarmmap.services.learner.pace`): its
    States go out as ``learner.slow_link_compression``; None where it keeps its encoding (one
    chosen already, none asked, or no link but memory)."""
    s, codec = learner.s, learner.codec
    if codec is None or s.transport != "zenoh" or s.compression != "none" or s.slow_link_compression == "none":
        return None

    def compress() -> str:
        codec.compressor = state_compressor(s, s.slow_link_compression, {}, list(codec.compressor.knobs.matrices))
        return s.slow_link_compression + (f" ({s.quant_bits} bits a value)" if s.slow_link_compression == "quant" else "")

    return compress


def state_links(learner: RobotLearner, link: Link, compressor: Encoder, coverage: Coverage | None) -> StateCodec:
    """A learner's links as its settings ask: faults injected where the run's ``faults`` say, States
    encoded (``learner.compression``) and numbered by training round (``learner.exchange_every``),
    and on a dynamic disk graph limited to the neighbours within ``comm_radius_m``."""
    s, robot, cfg = learner.s, learner.robot, learner.cfg
    if any_faults(cfg.faults):
        link = FaultyTransport(link, robot, cfg.faults)
    dynamic = cfg.graph().dynamic
    if not s.share_coverage:
        coverage = None
    if coverage is not None and (coverage.cells + 7) // 8 > MAX_COVERAGE_BYTES:
        log.warning("robot %d: coverage not shared: %d cells of %.2f m are more than a State may carry (%d bytes); "
                    "raise learner.unseen_margin_m to share it", robot, coverage.cells, coverage.cell, MAX_COVERAGE_BYTES)
        coverage = None
    return StateCodec(link, robot, compressor, s.exchange_every, radius=s.comm_radius_m if dynamic else None,
                      position=(lambda: learner.collector.position) if dynamic else None, coverage=coverage)


def refused_from(stats: ExchangeStats, bus: Bus) -> list[list[int]]:
    """[neighbour, messages of it refused], by a learner's exchange and its bus (malformed, muted)."""
    counts = Counter(stats.refused_from)
    for key, n in bus.dropped_on.items():
        if key.startswith(f"{bus.keys.root}/learners/"):
            counts[bus.keys.ident_of(key)] += n
    return [[j, n] for j, n in sorted(counts.items())][:128]


def hostile(cfg: RunConfig, robot: int, transport: Transport, layout: StateLayout,
            publish_metrics: Callable[[Metrics], object]) -> Transport:
    """``transport``, or, for a robot of ``faults.attackers``, one that lies to its neighbours (tests,
    bench/); a metrics-flood attacker floods ``publish_metrics`` too."""
    if robot not in cfg.faults.attackers or cfg.faults.attack == "none":
        return transport
    liar = HostileTransport(transport, robot, cfg.faults.attack, layout, cfg.faults.seed)
    if liar.liar.plugin.sends == "metrics":
        flood_metrics(publish_metrics, cfg.run_id, robot)
    return liar


def compute_slots(cfg: RunConfig, robot: int) -> AbstractContextManager:
    """Zenoh, one learner a process, by rounds: at most ``compute_slots`` of this host's learners
    train at once (on a clock a learner never waits for its neighbours: it would keep its slot)."""
    s = cfg.learner
    if s.compute_slots and s.transport == "zenoh" and not s.exchange_every_s:
        try:
            return ComputeSlots(slots_dir(cfg.run_id), s.compute_slots, home=robot)
        except OSError as exc:
            log.warning("robot %d: training without compute slots: %s", robot, exc)
    return nullcontext()


def exchange_bytes(bus: Bus, robot: int) -> tuple[int, int]:
    """Bytes ``robot`` sent and received on Algorithm 1's keys (State and RoundComplete) over Zenoh."""
    own = set(bus.keys.exchange(robot))
    return bus.sent.bytes_where(own.__contains__), bus.received.bytes_where(lambda key: bus.keys.is_exchange(key) and key not in own)


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The learner's main work; returns the process exit status."""
    s = cfg.learner
    inproc = s.transport == "inproc"
    robots = list(range(cfg.robots)) if inproc else [task_robot(s.robot, cfg.robots, "learner.robot")]
    if not inproc:  # (in process, one learner serves every robot: there is no robot's budget to fit)
        cfg, budget, traded = fit(cfg, robots[0])
        s = cfg.learner
        if budget.memory_bytes is not None or budget.cpus is not None:
            log.info("robot %d's budget: %s; %s", robots[0], budget, "; ".join(traded) if traded else "nothing to trade")
    torch.set_num_threads(s.torch_threads)
    device = pick_device(s.device)
    keys = Keys(cfg.key_prefix, cfg.run_id)
    with Bus.open(cfg.zenoh, keys, "learner", robots[0]) as bus:
        bus.end_with_run(stop)
        learners = [RobotLearner(cfg, r, bus, device) for r in robots]
        for r in robots:
            bus.announce(r)
        warm_up(s.optimizer)  # while the world starts and the robots drive
        world = bus.world(cfg.world_wait_s(), stop)
        if world is None:
            return 0 if stop.is_set() else 3
        where, packed = origin("consensus", s.consensus), origin("compressions", s.compression)
        log.info("robots %s (%s transport): model %s %s on %s, consensus %s%s, compression %s%s", robots, s.transport, s.model,
                 s.model_shape, device, s.consensus, f" (from {where})" if where else "", s.compression,
                 f" (from {packed})" if packed else "")
        try:
            for learner in learners:  # (every robot's, before any waits for its data: in process, one thread does both)
                learner.listen(world, stop)
            for learner in learners:
                learner.prepare(stop)
            if s.algorithm == "centralized":
                train_centralized(learners, stop)
            elif inproc:
                train_in_process(learners, stop)
            else:
                train_over_zenoh(bus, learners[0], stop)
        except LearnerError as exc:
            log.error("%s", exc)
            return exc.status
        except InterruptedError:
            log.info("robots %s: stopped", robots)
            return 0
        # Stay until the run is over (the recorder's run/done): a launcher that stops everything
        # once one service exits (compose's --exit-code-from) must not cut the others short.
        if inproc or s.algorithm == "centralized":
            stop.wait(s.peer_timeout_s if bus.alive("recorder") else 0.5)
    return 0


def train_in_process(learners: list[RobotLearner], stop: threading.Event) -> None:
    """Every robot's node in a thread of its own, over one in-memory hub that speaks the wire codec."""
    hub = MemoryHub({r.robot: r.neighbours for r in learners}, run=learners[0].cfg.run_id)
    transports = {}
    for r in learners:
        r.wire = MemoryLink(hub, r.robot)
        transports[r.robot] = r.compose(lambda layout, wire=r.wire: wire)
    run_all(learners, transports, stop)


def train_over_zenoh(bus: Bus, me: RobotLearner, stop: threading.Event) -> None:
    """One robot over Zenoh: subscribe to exactly its neighbours (known once the world answered),
    say so with an "exchange" token (neighbours start Algorithm 1 once they see it), train, then
    say the final State and Metrics again now and then until the run is over (``run/done``, or the
    recorder gone for ``peer_timeout_s``): a neighbour that restarts behind a finished team, however
    late, catches up to it (jumping to the final round, or replaying the rounds it lost with this
    node's States of them: :func:`answer_behind`), and a recorder cut off by a partition when this
    robot finished hears of it once the link is back (it keeps the first)."""
    s, cfg = me.s, me.cfg
    transport = me.compose(lambda layout: ZenohTransport(bus, me.robot, me.neighbours, layout.size, s.inbox_limit))
    if any_faults(cfg.faults):
        log.warning("robot %d: injecting faults on its incoming links: %s", me.robot, cfg.faults.model_dump())
    bus.announce(me.robot, service="exchange")
    missing = bus.wait_alive("exchange", {str(j) for j in me.neighbours}, s.peer_timeout_s, stop)
    if me.neighbours and missing == {str(j) for j in me.neighbours} and not stop.is_set():
        raise LearnerError(f"neighbour learner(s) {sorted(missing)} never became ready to exchange", 4)
    if missing:
        log.warning("robot %d: starting without neighbour(s) %s (not ready to exchange)", me.robot, sorted(missing))
    run_all([me], {me.robot: transport}, stop)
    if not bus.alive("recorder"):  # nobody will say the run is over
        stop.wait(0.5)
        return
    recorder_seen, final_round = time.monotonic(), s.rounds // s.exchange_every
    for j in me.stats.final_peers if me.replay is not None else ():  # (finished too: what they replay to others is no word)
        me.replay.seen(j, final_round)
    while not answer_behind(me, transport, final_round, time.monotonic() + s.resend_after_s, stop) \
            and time.monotonic() - recorder_seen < s.peer_timeout_s:
        me.codec.send_state(final_round, me.final_state, whole=True)  # (a key frame: rebuilt by anyone)
        me.metrics_pub.put(me.final_metrics)
        if bus.alive("recorder"):  # (gone for peer_timeout_s, e.g. cut off for good: leave)
            recorder_seen = time.monotonic()


def answer_behind(me: RobotLearner, transport: Transport, final_round: int, until: float, stop: threading.Event) -> bool:
    """A finished learner listens until ``until``: a neighbour that restarted behind it (its
    liveliness token vanished, then a State of an earlier round) gets this node's States of the
    rounds it replays, as during training (:class:`Replay`). Returns whether the run was stopped."""
    if me.replay is None:  # (the clock mode replays nothing)
        return stop.wait(max(0.0, until - time.monotonic()))
    while not stop.is_set() and (left := until - time.monotonic()) > 0:
        me.replay.forget(transport.lost_peers())
        msg = transport.receive(timeout=min(left, CHECK_EVERY_S))
        if msg is None or msg.kind != "state" or msg.sender not in me.neighbours:
            continue
        if me.replay.seen(msg.sender, msg.round) and msg.round < final_round:  # its newest word, behind this node
            me.replay.answer(msg.sender, msg.round, final_round, transport, time.monotonic())
    return stop.is_set()


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
