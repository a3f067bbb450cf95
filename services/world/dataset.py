"""The world of a run on real LiDAR logs (``world.dataset``): the logs' scans instead of a simulation.

Started as the world service (``swarmmap world`` with ``world.dataset`` set). It reads the logs
(:mod:`swarmmap.shared.world.datasets`: CARMEN logs, ROS 1 bags, rosbag2 folders, ``.mcap``), cuts them
into one contiguous segment per robot, holds every ``world.dataset_holdout_every``-th scan of
each robot out, and serves on ``world/map`` what a run needs of a world: the map's extent (every
hit within ``world.lidar_max_range_m`` and every pose, plus ``world.dataset_margin_m``), the
validation set (the held-out scans' beams) and the classic log-odds grid of every training scan
as the reference (``WorldMap.reference``; there is no ground truth). Once the services of
``world.wait_for`` are alive it publishes each robot's training scans on ``robots/<i>/scan`` in
the log's time order, at ``world.time_scale`` times the log's pace (0: as fast as the streamers
take them); each robot's last scan has ``last`` set. The streamers apply their sensor model as to
simulated scans (with the dataset defaults, no added noise or dropouts: the data is real).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from swarmmap.services.world.session import serving
from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Scan, Tensor, WorldMap
from swarmmap.shared.world.datasets import BagTopics, DatasetError, read_log
from swarmmap.shared.world.logodds import bce
from swarmmap.shared.world.teams import Team, make_team

log = logging.getLogger("world")

OCCUPIED_P, FREE_P = 0.65, 0.196  # map_saver's thresholds for the reference's trinary map


def load_team(cfg: RunConfig) -> Team:
    """The run's team from ``world.dataset``."""
    w = cfg.world
    topics = BagTopics(w.dataset_scan_topic, w.dataset_odom_topic, w.dataset_fixed_frame)
    logs = [read_log(path, w.dataset_pose, topics) for path in w.dataset]
    beams = cfg.labelling()
    return make_team(logs, cfg.robots, max_range=w.lidar_max_range_m, resolution=w.grid_resolution_m,
                     holdout_every=w.dataset_holdout_every, margin=w.dataset_margin_m,
                     samples_per_beam=beams.samples_per_beam, occupied_depth=beams.occupied_depth_m, val_beams=w.val_beams)


def trinary(p: np.ndarray) -> np.ndarray:
    """0 free, 1 occupied, 2 unknown from occupancy probabilities (map_saver's thresholds)."""
    return np.where(p >= OCCUPIED_P, np.uint8(1), np.where(p <= FREE_P, np.uint8(0), np.uint8(2)))


def world_map_message(cfg: RunConfig, team: Team) -> WorldMap:
    p = team.reference.probability()
    return WorldMap(run=cfg.run_id, sender=0, resolution=team.resolution, origin=list(team.origin),
                    grid=Tensor.of(trinary(p), "|u1"), val_points=Tensor.of(team.val_points, "<f4"),
                    val_labels=Tensor.of(team.val_labels, "<f4"), robots=cfg.robots,
                    positions=Tensor.of(team.positions(), "<f4"), reference=Tensor.of(p, "<f4"))


def describe(team: Team) -> None:
    """Log what the run is made of: logs, segments, map, validation set and the reference's score."""
    for log_ in dict.fromkeys(r.log for r in team.robots):
        log.info("dataset %s: %d scans of %d beams over %.0f s, no return at %.1f m%s", log_.source, len(log_),
                 len(log_.angles), log_.t[-1] - log_.t[0], log_.no_return_m,
                 "".join(f"; {n}" for n in log_.notes))
    for i, r in enumerate(team.robots):
        travelled = float(np.linalg.norm(np.diff(r.log.poses[r.train, :2], axis=0), axis=1).sum())
        segment = np.concatenate([r.train, r.held_out])
        log.info("robot %d: scans %d-%d of %s (%d trained on, %d held out), %.1f m driven", i, segment.min(), segment.max(),
                 r.log.source, len(r.train), len(r.held_out), travelled)
    h, w = team.shape
    ref = team.reference
    log.info("map: %d x %d cells of %.3f m from (%.1f, %.1f); log-odds grid of the training scans: %.0f%% of the cells "
             "seen; held-out validation set: %d points (%.1f%% occupied), log-odds grid's val_bce on it %.4f", w, h,
             team.resolution, *team.origin, 100 * ref.known().mean(), len(team.val_labels), 100 * team.val_labels.mean(),
             bce(ref.at(team.val_points), team.val_labels))


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The world service on a dataset; returns the process exit status."""
    w = cfg.world
    try:
        team = load_team(cfg)
    except DatasetError as exc:
        log.error("dataset refused: %s", exc)
        return 2
    describe(team)
    payload = encode(world_map_message(cfg, team))
    # Every robot's scans in the time order of its own segment (each starts at 0).
    events = sorted((team.time(i, k), i, k) for i, r in enumerate(team.robots) for k in range(len(r.train)))
    with serving(cfg, lambda _parameters: payload, stop) as pubs:
        if pubs is None:
            return 0
        start = time.monotonic()
        sent = 0
        for t, i, k in events:
            if stop.is_set():
                return 0
            if w.time_scale > 0 and (ahead := t / w.time_scale - (time.monotonic() - start)) > 0:
                stop.wait(ahead)
            _, pose, angles, ranges, hit = team.scan(i, k)
            reach = team.robots[i].log.reach(team.max_range)
            pubs[i].put(Scan(run=cfg.run_id, sender=i, seq=k, t=t, pose=[float(v) for v in pose], max_range=reach,
                             angles=Tensor.of(angles.astype(np.float32), "<f4"), ranges=Tensor.of(ranges, "<f4"),
                             hit=Tensor.of(hit.astype(np.uint8), "|u1"), last=k == len(team.robots[i].train) - 1))
            sent += 1
        log.info("dataset served: %d scans to %d robots in %.1f s", sent, cfg.robots, time.monotonic() - start)
        stop.wait()  # keep serving the map until told to stop
    return 0

