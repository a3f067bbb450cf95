"""A team's maps published on ROS 2 (``nav_msgs/OccupancyGrid``): what the observer and
``swarmmap ros2`` hand to RViz, Nav2 and map_saver. rclpy is imported when used (``swarmmap[ros2]``).

The maps follow ROS's conventions (:func:`ros_occupancy`): 0-100 with map_server's thresholds
(100 where the mean is at least ``occupied_thresh`` 0.65: a wall Nav2's static layer takes as
lethal; 0 at or below ``free_thresh`` 0.196; percent in between) and -1 where no beam of the team
went or where the model's std is at least ``ros2.unknown_std``."""

from __future__ import annotations

import array
import io
import threading
from pathlib import Path

import numpy as np

from swarmmap.shared.run.atomic import atomic_write_bytes
from swarmmap.shared.run.config import ConfigError
from swarmmap.shared.run.mapfiles import FREE_THRESH, OCCUPIED_THRESH
from swarmmap.shared.run.rosout import grid_values, team_map
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.sensing import along_beams


def ros_occupancy(mean: np.ndarray, std: np.ndarray | None, seen: np.ndarray | None, unknown_std: float) -> np.ndarray:
    """A learned map (H, W) as OccupancyGrid data (see the module): int8 (H*W,), row-major from the south-west cell."""
    mean = np.asarray(mean, np.float64)
    out = np.where(mean >= OCCUPIED_THRESH, 100, np.where(mean <= FREE_THRESH, 0, np.rint(100 * np.nan_to_num(mean))))
    unknown = np.isnan(mean)
    if seen is not None and seen.shape == mean.shape:
        unknown |= ~seen
    if std is not None:
        unknown |= np.asarray(std) >= unknown_std
    return np.where(unknown, -1, out).astype(np.int8).ravel()


def seen_cells(shape: tuple[int, int], origin: tuple[float, float], resolution: float, pose, angles: np.ndarray,
               ranges: np.ndarray) -> np.ndarray:
    """(H, W) bool: the cells one scan's beams crossed or ended in (``angles`` absolute)."""
    grid = OccupancyGrid(np.zeros(shape, np.uint8), resolution, tuple(origin))
    rows, cols, inside = grid.cells(along_beams(pose, angles, ranges, resolution / 2, through_end=True))
    out = np.zeros(shape, bool)
    out[rows[inside], cols[inside]] = True
    return out


def save_seen(path: Path, seen: np.ndarray, origin: tuple[float, float], resolution: float) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, seen=seen, origin=np.asarray(origin, np.float64), resolution=np.float64(resolution))
    atomic_write_bytes(path, buf.getvalue())


def need_rclpy():
    """rclpy, or a ConfigError saying how to get it."""
    try:
        import rclpy

        return rclpy
    except ImportError:
        raise ConfigError("config error:\n  ros2: needs rclpy: pip install 'swarmmap[ros2]' (rclpy with Fast DDS from PyPI), "
                          "or source a ROS 2 install") from None


class Ros2Maps:
    """The observer's ROS 2 publisher of every robot's maps and the team's (a :class:`MapSink`); on
    close, the cells the team's beams went are kept in ``seen_path`` (for the maps served after the run)."""

    name = "ros2"
    every_scan = True  # (the cells nobody saw are -1: every scan counts)

    def __init__(self, namespaces: list[str], std_max: float, unknown_std: float = 0.2, seen_path: Path | None = None):
        rclpy = need_rclpy()
        self.std_max, self.unknown_std, self.seen_path = std_max, unknown_std, seen_path
        self.pub = GridPublisher(rclpy, "swarmmap_maps")
        self.path = ", ".join(f"/{ns}" for ns in namespaces)
        self.topics = {i: (f"/{ns}/map", f"/{ns}/map_std") for i, ns in enumerate(namespaces)}
        self.info: tuple | None = None
        self.seen: np.ndarray | None = None
        self.team: dict[int, np.ndarray] = {}
        self.team_std: dict[int, np.ndarray] = {}
        self.lock = threading.Lock()
        self.closed = False

    def world(self, resolution, origin, shape, reference) -> None:
        self.info = (float(resolution), (float(origin[0]), float(origin[1])), tuple(int(v) for v in shape))
        self.seen = np.zeros(self.info[2], bool)

    def scan(self, robot, pose, angles, ranges, hit, max_range) -> None:
        if self.info is None:
            return
        res, origin, shape = self.info
        cells = seen_cells(shape, origin, res, pose, np.asarray(angles, np.float64), np.asarray(ranges, np.float64))
        with self.lock:
            self.seen |= cells

    def maps(self, robot: int, mean: np.ndarray, std: np.ndarray | None) -> None:
        with self.lock:
            if self.closed or self.info is None or robot not in self.topics:
                return
            map_topic, std_topic = self.topics[robot]
            self.pub.publish(map_topic, self.info, ros_occupancy(mean, std, self.seen, self.unknown_std))
            if std is not None:
                self.pub.publish(std_topic, self.info, grid_values(std, self.std_max))
                self.team_std[robot] = std
            self.team[robot] = mean
            team_std = team_map(self.team_std) if len(self.team_std) == len(self.team) else None
            self.pub.publish("/map", self.info, ros_occupancy(team_map(self.team), team_std, self.seen, self.unknown_std))

    def close(self) -> dict[str, int]:
        with self.lock:
            if not self.closed:
                self.closed = True
                self.pub.close()
                if self.seen_path is not None and self.info is not None:
                    save_seen(self.seen_path, self.seen, self.info[1], self.info[0])
            return dict(self.pub.counts)


class GridPublisher:
    """An rclpy node with a reliable, transient-local ``nav_msgs/OccupancyGrid`` publisher per topic
    it publishes on (a node that subscribes later gets the newest)."""

    def __init__(self, rclpy, name: str):
        from nav_msgs.msg import OccupancyGrid
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.rclpy, self.Grid = rclpy, OccupancyGrid
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pubs: dict[str, object] = {}  # (a topic is advertised when it has a map: no map_std without a std)
        self.counts: dict[str, int] = {}

    def publish(self, topic: str, info: tuple, data: np.ndarray) -> None:
        """``data`` (int8 (H*W,)) on ``topic``; ``info`` = (resolution, (x0, y0), (H, W)), frame ``map``."""
        from geometry_msgs.msg import Pose
        from nav_msgs.msg import MapMetaData

        res, (ox, oy), (h, w) = info
        msg = self.Grid()
        now = self.node.get_clock().now().to_msg()
        msg.header.stamp, msg.header.frame_id = now, "map"
        origin = Pose()
        origin.position.x, origin.position.y, origin.orientation.w = float(ox), float(oy), 1.0
        msg.info = MapMetaData(map_load_time=now, resolution=float(res), width=int(w), height=int(h), origin=origin)
        msg.data = array.array("b", np.asarray(data, np.int8).tobytes())
        if topic not in self.pubs:
            self.pubs[topic] = self.node.create_publisher(self.Grid, topic, self.qos)
        self.pubs[topic].publish(msg)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)
