"""A LiDAR streamer: one robot's scans in, labelled training points out.

Run-book: ``swarmmap lidar --robot I --config RUN_DIR/config.yaml``. It subscribes to
``robots/<I>/scan``, turns each scan into free samples along the beams and an occupied point
at each hit (:func:`swarmmap.shared.sensing.beam_samples`) and publishes them as ``Samples``
on ``robots/<I>/samples``; the end of the robot's traversal is passed on as ``last``.
"""

from __future__ import annotations

import logging
import queue
import threading

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig, fail
from swarmmap.shared.protocol import Keys, Samples, Scan, Tensor
from swarmmap.shared.sensing import beam_samples

log = logging.getLogger("lidar")


def scan_to_samples(scan: Scan, cfg: RunConfig) -> Samples:
    """The labelled points of one scan."""
    pose = scan.pose
    points, labels = beam_samples(pose[:2], scan.angles.numpy(), scan.ranges.numpy(), scan.hit.numpy().astype(bool),
                                  scan.max_range, cfg.lidar.samples_per_beam, cfg.lidar.occupied_depth_m)
    return Samples(run=scan.run, sender=scan.sender, seq=scan.seq, t=scan.t, position=list(pose[:2]),
                   points=Tensor.of(points, "<f4"), labels=Tensor.of(labels, "<f4"), last=scan.last)


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The streamer's main loop; returns the process exit status."""
    robot = cfg.lidar.robot
    if robot is None or robot >= cfg.robots:
        fail(f"config error:\n  lidar.robot: required, one of 0..{cfg.robots - 1} (got {robot!r})")
    keys = Keys(cfg.key_prefix, cfg.run_id)
    inbox: queue.Queue[Scan] = queue.Queue()
    with Bus.open(cfg.zenoh, keys, "lidar", robot) as bus:
        out = bus.publisher(keys.samples(robot))
        bus.subscribe(keys.scan(robot), Scan, inbox.put)
        bus.announce()
        count = points = 0
        while not stop.is_set():
            try:
                scan = inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            samples = scan_to_samples(scan, cfg)
            out.put(samples)
            count += 1
            points += samples.labels.shape[0]
            if scan.last:
                log.info("robot %d traversal done: %d scans -> %d labelled points", robot, count, points)
    return 0
