"""A team's maps published on ROS 2 (``nav_msgs/OccupancyGrid``): what the observer and
``swarmmap ros2`` hand to RViz, Nav2 and map_saver. rclpy is imported when used (``swarmmap[ros2]``)."""

from __future__ import annotations

import array
import threading

import numpy as np

from swarmmap.shared.run.config import ConfigError
from swarmmap.shared.run.rosout import grid_values, team_map


def need_rclpy():
    """rclpy, or a ConfigError saying how to get it."""
    try:
        import rclpy

        return rclpy
    except ImportError:
        raise ConfigError("config error:\n  ros2: needs rclpy: pip install 'swarmmap[ros2]' (rclpy with Fast DDS from PyPI), "
                          "or source a ROS 2 install") from None


class Ros2Maps:
    """The observer's ROS 2 publisher of every robot's maps and the team's (a :class:`MapSink`)."""

    name = "ros2"

    def __init__(self, namespaces: list[str], std_max: float):
        rclpy = need_rclpy()
        from nav_msgs.msg import OccupancyGrid
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.rclpy, self.Grid, self.std_max = rclpy, OccupancyGrid, std_max
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("swarmmap_maps", context=self.context)
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.path = ", ".join(f"/{ns}" for ns in namespaces)
        self.pubs = {i: (self.node.create_publisher(OccupancyGrid, f"/{ns}/map", qos),
                         self.node.create_publisher(OccupancyGrid, f"/{ns}/map_std", qos)) for i, ns in enumerate(namespaces)}
        self.topics = {i: (f"/{ns}/map", f"/{ns}/map_std") for i, ns in enumerate(namespaces)}
        self.team_pub = self.node.create_publisher(OccupancyGrid, "/map", qos)
        self.info: tuple | None = None
        self.team: dict[int, np.ndarray] = {}
        self.counts: dict[str, int] = {}
        self.lock = threading.Lock()
        self.closed = False

    def world(self, resolution, origin, shape, reference) -> None:
        self.info = (float(resolution), (float(origin[0]), float(origin[1])), tuple(int(v) for v in shape))

    def scan(self, robot, pose, angles, ranges, hit, max_range) -> None:
        pass  # the robots' scans are on ROS 2 already

    def _publish(self, pub, topic: str, data: np.ndarray) -> None:
        from geometry_msgs.msg import Pose
        from nav_msgs.msg import MapMetaData

        res, (ox, oy), (h, w) = self.info
        msg = self.Grid()
        now = self.node.get_clock().now().to_msg()
        msg.header.stamp, msg.header.frame_id = now, "map"
        origin = Pose()
        origin.position.x, origin.position.y, origin.orientation.w = ox, oy, 1.0
        msg.info = MapMetaData(map_load_time=now, resolution=res, width=w, height=h, origin=origin)
        msg.data = array.array("b", data.astype(np.int8).tobytes())
        pub.publish(msg)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def maps(self, robot: int, mean: np.ndarray, std: np.ndarray | None) -> None:
        with self.lock:
            if self.closed or self.info is None or robot not in self.pubs:
                return
            self._publish(self.pubs[robot][0], self.topics[robot][0], grid_values(mean))
            if std is not None:
                self._publish(self.pubs[robot][1], self.topics[robot][1], grid_values(std, self.std_max))
            self.team[robot] = mean
            self._publish(self.team_pub, "/map", grid_values(team_map(self.team)))

    def close(self) -> dict[str, int]:
        with self.lock:
            if not self.closed:
                self.closed = True
                self.node.destroy_node()
                self.rclpy.shutdown(context=self.context)
            return dict(self.counts)
