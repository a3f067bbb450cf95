"""Real logs as a team: each log's scans cut into contiguous time segments, one per robot, and
every ``holdout_every``-th scan of each segment held out (never trained on, :func:`split_team`);
with the map's grid, the log-odds reference of the training scans and the held-out validation set
(:func:`make_team`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from swarmmap.shared.world.datasets import DatasetError, LaserLog

if TYPE_CHECKING:
    from swarmmap.shared.world.logodds import LogOddsGrid


@dataclass
class RobotData:
    """One robot's share of a log: the scans it trains on and the ones held out from it."""

    log: LaserLog
    train: np.ndarray
    held_out: np.ndarray


def split_team(logs: list[LaserLog], robots: int, holdout_every: int) -> list[RobotData]:
    """``robots`` robots from ``logs``: each log gives ``robots / len(logs)`` robots, each a
    contiguous segment of its scans in time (equal numbers of scans); every ``holdout_every``-th
    scan of a segment is held out (0: none)."""
    if robots % len(logs):
        raise DatasetError(logs[0].source, f"{robots} robots from {len(logs)} logs: give a multiple of {len(logs)} "
                                           "(each log gives the same number of robots)")
    per = robots // len(logs)
    out = []
    for log in logs:
        if len(log) < 2 * per:
            raise DatasetError(log.source, f"{len(log)} scans cannot make {per} robots of at least 2 scans")
        for seg in np.array_split(np.arange(len(log)), per):
            held = np.zeros(len(seg), bool)
            if holdout_every > 0:
                held[holdout_every - 1 :: holdout_every] = True
            out.append(RobotData(log, seg[~held], seg[held]))
    return out


@dataclass
class Team:
    """A team made of real logs: each robot's training scans, the held-out validation set and the
    log-odds grid of every training scan, over a map that covers every hit and pose."""

    robots: list[RobotData]
    max_range: float
    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]
    reference: LogOddsGrid
    val_points: np.ndarray
    val_labels: np.ndarray

    def scan(self, robot: int, k: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Robot ``robot``'s ``k``-th training scan: (time from its first, pose (3,), absolute
        angles, ranges, hit) of its valid beams."""
        r = self.robots[robot]
        i = r.train[k]
        ranges, hit, valid = r.log.hits(self.max_range)
        angles = r.log.poses[i, 2] + r.log.angles
        return (self.time(robot, k), r.log.poses[i], angles[valid[i]], ranges[i][valid[i]],
                hit[i][valid[i]])

    def time(self, robot: int, k: int) -> float:
        """Seconds from robot ``robot``'s first training scan to its ``k``-th."""
        r = self.robots[robot]
        return float(r.log.t[r.train[k]] - r.log.t[r.train[0]])

    def positions(self) -> np.ndarray:
        """(robots, 2) where each robot's segment ends."""
        return np.array([r.log.poses[r.train[-1], :2] for r in self.robots], np.float32)


def beams_of(log: LaserLog, scans: np.ndarray, max_range: float, every: int = 1):
    """Positions (N, 2), absolute angles, ranges and hit (N, B') of ``scans`` of ``log``, every
    ``every``-th beam; invalid beams come back with range 0 and no hit (they mark nothing)."""
    ranges, hit, valid = log.hits(max_range)
    cols = slice(None, None, every)
    angles = log.poses[scans, 2:3] + log.angles[None, cols]
    v = valid[scans][:, cols]
    return log.poses[scans, :2], angles, np.where(v, ranges[scans][:, cols], 0.0), hit[scans][:, cols] & v


def make_team(logs: list[LaserLog], robots: int, *, max_range: float, resolution: float, holdout_every: int,
              margin: float, samples_per_beam: int, occupied_depth: float, val_beams: int,
              extent: tuple[float, float, float, float] | None = None) -> Team:
    """The team of :func:`split_team` with its map grid, reference grid and held-out validation set
    (every ``holdout_every``-th scan's hitting beams, about ``val_beams`` a scan, labelled along
    the beam as the streamers label training points). The map covers every hit and pose plus
    ``margin``, or ``extent`` (xmin, ymin, xmax, ymax) where given."""
    from swarmmap.shared.world.logodds import build_logodds
    from swarmmap.shared.world.sensing import beam_samples

    team = split_team(logs, robots, holdout_every)
    ends = np.concatenate([lg.endpoints(max_range) for lg in logs] + [lg.poses[:, :2] for lg in logs])
    lo, hi = ends.min(0) - margin, ends.max(0) + margin
    if extent is not None:
        lo, hi = np.array(extent[:2], np.float64), np.array(extent[2:], np.float64)
    shape = (int(math.ceil((hi[1] - lo[1]) / resolution)), int(math.ceil((hi[0] - lo[0]) / resolution)))
    if shape[0] * shape[1] > 40_000_000:
        raise DatasetError(logs[0].source, f"a map of {shape[1]} x {shape[0]} cells at {resolution} m: too large "
                                           "(raise world.grid_resolution_m or lower world.lidar_max_range_m)")
    origin = (float(lo[0]), float(lo[1]))
    parts = [beams_of(r.log, r.train, max_range) for r in team]
    reference = build_logodds(shape, origin, resolution, np.concatenate([p[0] for p in parts]),
                              np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]),
                              np.concatenate([p[3] for p in parts]))
    points, labels = [], []
    for r in team:
        every = max(1, len(r.log.angles) // max(val_beams, 1))
        pos, angles, ranges, hit = beams_of(r.log, r.held_out, max_range, every)
        for k in range(len(pos)):
            if hit[k].any():
                p, lab = beam_samples(pos[k], angles[k][hit[k]], ranges[k][hit[k]], np.ones(int(hit[k].sum()), bool),
                                      max_range, samples_per_beam, occupied_depth)
                points.append(p)
                labels.append(lab)
    if not points:
        raise DatasetError(logs[0].source, f"no held-out beam hits anything within {max_range} m: no validation set")
    return Team(team, max_range, origin, resolution, shape, reference, np.concatenate(points).astype(np.float32),
                np.concatenate(labels).astype(np.float32))
