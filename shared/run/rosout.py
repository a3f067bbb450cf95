"""A run in ROS terms: learned maps as ``nav_msgs/OccupancyGrid``, scans as ``sensor_msgs/LaserScan``,
poses as ``tf``; and :class:`McapBag`, which writes them to a rosbag2 in MCAP (Foxglove and
``ros2 bag play`` open it).

Topics (``<i>`` a robot id), every one in frame ``map``:

- ``/robot_<i>/map``: the robot's learned mean occupancy, 0-100 (percent), -1 nowhere;
  ``/robot_<i>/map_std``: its standard deviation on the scale ``100 * std / std_max``
  (``observer.std_max``, 0.25 by default: 100 means a std of 0.25 or more), for a model with one;
- ``/map``: the team's map, the mean of every robot's newest mean map;
- ``/reference``: the plan's ground truth, or on a dataset the log-odds grid (trinary: 0 free,
  100 occupied, -1 unknown), once;
- ``/robot_<i>/scan``: its LiDAR scans (frame ``robot_<i>/base_scan``; +inf where a beam saw
  nothing, NaN where it gave no reading), ``/robot_<i>/pose`` (``geometry_msgs/PoseStamped``)
  and ``/tf`` (``map`` -> ``robot_<i>/base_scan``).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np


def grid_values(values: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """``values`` (H, W) as OccupancyGrid data, row-major from the south-west cell: round(100 *
    value / scale) clipped to 0-100, -1 where NaN; int8 (H*W,)."""
    v = np.asarray(values, np.float64) / scale
    out = np.clip(np.rint(100 * np.nan_to_num(v, nan=0.0)), 0, 100).astype(np.int8)
    out[np.isnan(v)] = -1
    return out.ravel()


def trinary_values(grid: np.ndarray) -> np.ndarray:
    """A WorldMap grid (0 free, 1 occupied, 2 unknown) as OccupancyGrid data (0, 100, -1)."""
    return np.select([grid == 0, grid == 1], [0, 100], -1).astype(np.int8).ravel()


@dataclass(frozen=True)
class ScanArrays:
    """A scan as LaserScan carries it: evenly spaced beams relative to the heading."""

    angle_min: float
    angle_increment: float
    ranges: np.ndarray  # float32: +inf no return, NaN no reading


def scan_arrays(yaw: float, angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray) -> ScanArrays:
    """A Scan's beams (absolute ``angles``, possibly with gaps where beams gave no reading)
    laid out evenly from its first beam relative to ``yaw``."""
    rel = np.angle(np.exp(1j * (np.asarray(angles, np.float64) - yaw)))
    if len(rel) > 1:
        rel = rel[0] + np.unwrap(rel - rel[0])
    steps = np.diff(rel)
    inc = float(np.min(np.abs(steps[np.abs(steps) > 1e-6]))) * (1 if np.median(steps) > 0 else -1) if len(rel) > 1 else 0.0
    idx = np.rint((rel - rel[0]) / inc).astype(np.int64) if inc else np.zeros(len(rel), np.int64)
    out = np.full(int(idx.max(initial=0)) + 1, np.nan, np.float32)
    out[idx] = np.where(np.asarray(hit, bool), ranges, np.inf)
    return ScanArrays(float(rel[0]) if len(rel) else 0.0, inc, out)


class MapSink(Protocol):
    """Where the observer sends what it maps besides Rerun (:class:`McapBag`, the ROS 2 publisher)."""

    name: str
    path: str | Path
    every_scan: bool  # it takes every scan (else every ``observer.scan_every``-th and each robot's last)

    def world(self, resolution: float, origin: tuple[float, float], shape: tuple[int, int], reference: np.ndarray) -> None:
        """The grid every map is laid on and the reference (trinary, the grid's shape)."""

    def scan(self, robot: int, pose, angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray, max_range: float) -> None:
        """One scan of ``robot`` at ``pose`` (x, y, yaw)."""

    def maps(self, robot: int, mean: np.ndarray, std: np.ndarray | None) -> None:
        """A robot's learned maps (H, W) on the grid."""

    def close(self) -> dict[str, int]:
        """Finish; the messages sent per topic."""


def team_map(maps: dict[int, np.ndarray]) -> np.ndarray:
    """The team's map: the mean of every robot's newest mean map."""
    return np.mean(list(maps.values()), axis=0)


class McapBag:
    """A rosbag2 folder in MCAP that the observer writes a run into, thread-safe; refuses an
    existing folder (nothing already written is overwritten)."""

    name = "mcap"
    every_scan = False

    def __init__(self, path: str | Path, std_max: float):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.path, self.std_max = Path(path), std_max
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists: the bag of another run? give a new folder")
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T = self.ts.types
        self.lock = threading.Lock()
        self.writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.conns: dict[str, object] = {}
        self.team: dict[int, np.ndarray] = {}
        self.counts: dict[str, int] = {}
        self.info: tuple[float, tuple[float, float], tuple[int, int]] | None = None
        self.closed = False

    # ------------------------------------------------------------------ messages
    def _write(self, topic: str, msgtype: str, msg, stamp_ns: int) -> None:
        with self.lock:
            if self.closed:
                return
            if topic not in self.conns:
                self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
            self.writer.write(self.conns[topic], stamp_ns, self.ts.serialize_cdr(msg, msgtype))
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def _header(self, stamp_ns: int, frame: str):
        T = self.T
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
                                        frame_id=frame)

    def _pose(self, x: float, y: float, yaw: float):
        T = self.T
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                                                         w=math.cos(yaw / 2)))

    def _grid(self, topic: str, data: np.ndarray, stamp_ns: int) -> None:
        T = self.T
        res, (ox, oy), (h, w) = self.info
        meta = T["nav_msgs/msg/MapMetaData"](map_load_time=self._header(stamp_ns, "").stamp, resolution=float(res),
                                             width=int(w), height=int(h), origin=self._pose(ox, oy, 0.0))
        self._write(topic, "nav_msgs/msg/OccupancyGrid",
                    T["nav_msgs/msg/OccupancyGrid"](header=self._header(stamp_ns, "map"), info=meta, data=data), stamp_ns)

    # ------------------------------------------------------------------ what the observer sees
    def world(self, resolution: float, origin: tuple[float, float], shape: tuple[int, int], reference: np.ndarray,
              stamp_ns: int | None = None) -> None:
        """The map grid the learned maps are laid on and the reference (trinary, the grid's shape)."""
        self.info = (resolution, (float(origin[0]), float(origin[1])), tuple(shape))
        self._grid("/reference", trinary_values(reference), stamp_ns or time.time_ns())

    def scan(self, robot: int, pose: tuple[float, float, float], angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray,
             max_range: float, stamp_ns: int | None = None) -> None:
        """One scan of ``robot`` at ``pose`` (x, y, yaw in the map): LaserScan, PoseStamped, tf."""
        T, stamp = self.T, stamp_ns or time.time_ns()
        x, y, yaw = (float(v) for v in pose)
        frame = f"robot_{robot}/base_scan"
        arr = scan_arrays(yaw, angles, ranges, hit)
        n = len(arr.ranges)
        msg = T["sensor_msgs/msg/LaserScan"](header=self._header(stamp, frame), angle_min=arr.angle_min,
                                             angle_max=arr.angle_min + arr.angle_increment * (n - 1),
                                             angle_increment=arr.angle_increment, time_increment=0.0, scan_time=0.0,
                                             range_min=0.0, range_max=float(max_range), ranges=arr.ranges,
                                             intensities=np.zeros(0, np.float32))
        self._write(f"/robot_{robot}/scan", "sensor_msgs/msg/LaserScan", msg, stamp)
        self._write(f"/robot_{robot}/pose", "geometry_msgs/msg/PoseStamped",
                    T["geometry_msgs/msg/PoseStamped"](header=self._header(stamp, "map"), pose=self._pose(x, y, yaw)), stamp)
        q = self._pose(x, y, yaw).orientation
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, "map"), child_frame_id=frame,
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0), rotation=q))
        self._write("/tf", "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=[tf]), stamp)

    def maps(self, robot: int, mean: np.ndarray, std: np.ndarray | None, stamp_ns: int | None = None) -> None:
        """A robot's learned maps (H, W) on the grid of :meth:`world`, and the team's map anew."""
        if self.info is None:
            return
        stamp = stamp_ns or time.time_ns()
        self._grid(f"/robot_{robot}/map", grid_values(mean), stamp)
        if std is not None:
            self._grid(f"/robot_{robot}/map_std", grid_values(std, self.std_max), stamp)
        with self.lock:
            self.team[robot] = mean
            team = team_map(self.team)
        self._grid("/map", grid_values(team), stamp)

    def close(self) -> dict[str, int]:
        """Finish the bag; returns the messages written per topic."""
        with self.lock:
            if not self.closed:
                self.closed = True
                self.writer.close()
            return dict(self.counts)
