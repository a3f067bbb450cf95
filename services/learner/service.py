"""The learner service: one robot's DiNNO training over Zenoh (the paper's Algorithm 1).

Run-book: ``swarmmap learner --robot I --config RUN_DIR/config.yaml``. Order of work:

1. subscribe to its training points (``robots/<I>/samples``) and its neighbours' State and
   RoundComplete keys, then announce itself (liveliness ``alive/learner/<I>``);
2. fetch the ground-truth validation set from the world (query ``world/map``);
3. collect points until its robot's traversal ends (offline training, as in the paper);
4. wait for its neighbours to be alive, then run Algorithm 1 for ``rounds`` rounds with
   DiNNO's node update, publishing ``Metrics`` every ``eval_every`` rounds and at the end;
5. write ``RUN_DIR/models/robot-<I>.pt``, ``RUN_DIR/maps/robot-<I>-mean.png`` and its training
   points ``RUN_DIR/data/robot-<I>.npz``.
"""

from __future__ import annotations

import io
import logging
import os
import threading
import time

import numpy as np
import torch

from swarmmap.services.learner.dinno import DinnoNode, consensus_error, validation_bce
from swarmmap.services.learner.exchange import ExchangeStats, PeerFailure, run_algorithm1
from swarmmap.services.learner.zenoh_transport import ZenohTransport
from swarmmap.shared.atomic import atomic_write_bytes, save_png
from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig, fail
from swarmmap.shared.floorplan import OccupancyGrid
from swarmmap.shared.models import build_model, param_count, pick_device, predict, save_model, set_flat
from swarmmap.shared.protocol import Keys, Metrics, Samples, WorldMap

log = logging.getLogger("learner")


def neighbours_of(robot: int, robots: int, graph: str) -> set[int]:
    """The neighbours of ``robot`` in the communication graph."""
    if graph == "complete":
        return set(range(robots)) - {robot}
    if graph == "ring":
        return {(robot - 1) % robots, (robot + 1) % robots} - {robot}
    raise ValueError(f"unknown graph {graph!r}; allowed: complete, ring")


def exchange_bytes(bus: Bus) -> tuple[int, int]:
    """Bytes sent and received on Algorithm 1's keys (State and RoundComplete)."""

    def exchange(key: str) -> bool:
        return key.endswith(("/state", "/round-complete"))

    return bus.sent.bytes_where(exchange), bus.received.bytes_where(exchange)


class Collector:
    """Buffers a robot's Samples until the one marked ``last``."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        self.done = threading.Event()
        self._lock = threading.Lock()

    def add(self, msg: Samples) -> None:
        with self._lock:
            self.points.append(msg.points.numpy())
            self.labels.append(msg.labels.numpy())
        if msg.last:
            self.done.set()

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            if not self.points:
                return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
            return np.concatenate(self.points), np.concatenate(self.labels)


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The learner's main work; returns the process exit status."""
    s = cfg.learner
    robot = s.robot
    if robot is None or robot >= cfg.robots:
        fail(f"config error:\n  learner.robot: required, one of 0..{cfg.robots - 1} (got {robot!r})")
    torch.set_num_threads(s.torch_threads)
    device = pick_device(s.device)
    keys = Keys(cfg.key_prefix, cfg.run_id)
    neighbours = neighbours_of(robot, cfg.robots, s.graph)
    n_params = param_count(build_model(s.model_shape, s.siren_scale, (0, 0, 1, 1), cfg.seed))
    collector = Collector()
    with Bus.open(cfg.zenoh, keys, "learner", robot) as bus:
        bus.subscribe(keys.samples(robot), Samples, collector.add)
        transport = ZenohTransport(bus, robot, neighbours, n_params)
        metrics_pub = bus.publisher(keys.metrics(robot))
        bus.announce()
        world = bus.query(keys.world_map(), WorldMap, timeout=s.collect_timeout_s, stop=stop)
        if world is None:
            if stop.is_set():
                return 0
            log.error("no reply from the world on %s within %.0f s", keys.world_map(), s.collect_timeout_s)
            return 3
        log.info("robot %d: %d neighbours %s, model %s (%d parameters) on %s", robot, len(neighbours),
                 sorted(neighbours), s.model_shape, n_params, device)
        if not (collector.done.wait(s.collect_timeout_s) or stop.is_set()):
            log.error("robot %d: the traversal did not end within %.0f s (no Samples with last=true on %s)",
                      robot, s.collect_timeout_s, keys.samples(robot))
            return 3
        if stop.is_set():
            return 0
        points, labels = collector.arrays()
        if len(points) == 0:
            log.error("robot %d: the traversal ended without a single training point", robot)
            return 3
        log.info("robot %d: %d training points (%.1f%% occupied)", robot, len(points), 100 * labels.mean())
        model = build_model(s.model_shape, s.siren_scale, world.bounds, cfg.seed).to(device)
        node = DinnoNode(model, torch.from_numpy(points.copy()), torch.from_numpy(labels.copy()), s,
                         seed=cfg.seed * 1000 + robot + 1)
        val_x = torch.from_numpy(world.val_points.numpy().copy()).to(device)
        val_y = torch.from_numpy(world.val_labels.numpy().copy()).to(device)
        missing = bus.wait_alive("learner", {str(j) for j in neighbours}, s.peer_timeout_s, stop)
        if missing and not stop.is_set():
            log.error("robot %d: neighbour learner(s) %s never came alive", robot, sorted(missing))
            return 4

        stats = ExchangeStats()
        compute = {"s": 0.0}
        t_start = time.monotonic()

        def publish_metrics(k: int, theta: np.ndarray, peers: dict[int, np.ndarray], final: bool = False) -> Metrics:
            sent, received = exchange_bytes(bus)
            msg = Metrics(run=cfg.run_id, sender=robot, round=k, wall_time_s=time.monotonic() - t_start,
                          val_bce=validation_bce(node.model, val_x, val_y),
                          consensus_error=consensus_error(theta, peers), bytes_sent=sent, bytes_received=received,
                          compute_s=compute["s"], wait_s=stats.wait_s, send_s=stats.send_s,
                          n_points=len(points), pid=os.getpid(), final=final)
            metrics_pub.put(msg)
            return msg

        def node_update(k: int, theta: np.ndarray, peers: dict[int, np.ndarray]) -> np.ndarray:
            if k % s.eval_every == 0:
                m = publish_metrics(k, theta, peers)
                log.info("robot %d round %d: val_bce %.4f consensus %.4f", robot, k, m.val_bce, m.consensus_error)
            t0 = time.perf_counter()
            out = node.update(k, theta, peers)
            compute["s"] += time.perf_counter() - t0
            return out

        try:
            final = run_algorithm1(robot, neighbours, s.rounds, node.state(), node_update, transport, stats=stats,
                                   stop=stop, peer_timeout=s.peer_timeout_s, resend_after=s.resend_after_s)
        except PeerFailure as exc:
            log.error("%s", exc)
            return 5
        except InterruptedError:
            log.info("robot %d: stopped", robot)
            return 0
        set_flat(node.model, torch.from_numpy(final))
        m = publish_metrics(s.rounds, final, stats.final_peers, final=True)
        log.info("robot %d done: %d rounds in %.1f s, val_bce %.4f (compute %.1f s, waiting %.1f s, sending %.1f s)",
                 robot, s.rounds, m.wall_time_s, m.val_bce, m.compute_s, m.wait_s, m.send_s)
        if cfg.run_dir is not None:
            write_outputs(cfg, robot, node.model, world, points, labels)
        # Stay until every neighbour has its final State from us (they linger likewise).
        stop.wait(0.5)
    return 0


def write_outputs(cfg: RunConfig, robot: int, model, world: WorldMap, points: np.ndarray, labels: np.ndarray) -> None:
    """The model checkpoint, its mean map PNG and the robot's training points, written atomically."""
    run_dir = cfg.run_dir
    buf = io.BytesIO()
    np.savez_compressed(buf, points=points, labels=labels)
    atomic_write_bytes(run_dir / "data" / f"robot-{robot}.npz", buf.getvalue())
    save_model(model, run_dir / "models" / f"robot-{robot}.pt", robot=robot, rounds=cfg.learner.rounds,
               run_id=cfg.run_id)
    grid = OccupancyGrid(world.grid.numpy(), world.resolution, tuple(world.origin))
    pts, (h, w) = grid.centres(cfg.learner.map_resolution_m)
    save_png(run_dir / "maps" / f"robot-{robot}-mean.png", predict(model, pts).reshape(h, w))
