"""ROS 2 robots as the world hears them (``swarmmap ros2``): their scans at their poses in the
team's shared frame, and where their goals go. rclpy is imported when used (``swarmmap[ros2]``).

Per namespace it subscribes to ``/<ns>/<ros2.scan_topic>`` (``sensor_msgs/LaserScan``) and
``/<ns>/<ros2.odom_topic>`` (``nav_msgs/Odometry``), best effort as a sensor publishes (a reliable
publisher matches too), and to ``/tf_static`` and ``/<ns>/tf_static`` (transient local: where the
LiDAR sits on the base). A scan's pose is its robot's odometry at the scan's stamp (interpolated;
a scan waits until odometry at or past its stamp has come), moved by the LiDAR's mount (the static
transform from the odometry's child frame to the scan's frame) and by the robot's odometry origin
in the shared frame (``ros2.initial_poses``). It publishes ``map`` -> each robot's odometry frame
on ``/tf_static`` and each goal as ``geometry_msgs/PoseStamped`` on ``/<ns>/goal_pose`` (frame
``map``: Nav2's topic). Everything heard is kept (``ros2.max_scans`` scans a robot) and written
on :meth:`RosRobots.close` as a rosbag2 per robot, its poses in the shared frame.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import threading
import time
from pathlib import Path

import numpy as np

from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.rosmaps import need_rclpy
from swarmmap.shared.world.datasets import (
    BagMessages,
    BagTopics,
    DatasetError,
    LaserLog,
    PoseTrack,
    _chain,
    _compose,
    messages_log,
    write_rosbag,
)

log = logging.getLogger("world")
ODOM_KEPT = 2000  # odometry messages a scan's pose is interpolated from (the newest)
PENDING_MAX = 1000  # scans of a robot waiting for odometry past them; beyond, the oldest are dropped


def join(logs: list[LaserLog], source: str) -> LaserLog | None:
    """One LaserLog of several in time order (those with the first's beams), or None when empty."""
    logs = [x for x in logs if len(x)]
    if not logs:
        return None
    first = logs[0]
    same = [x for x in logs if len(x.angles) == len(first.angles) and np.allclose(x.angles, first.angles)]
    return LaserLog(source=source, t=np.concatenate([x.t for x in same]), poses=np.concatenate([x.poses for x in same]),
                    angles=first.angles, ranges=np.concatenate([x.ranges for x in same]), no_return_m=first.no_return_m,
                    min_range_m=min(x.min_range_m for x in same), scan_frame=first.scan_frame)


@dataclasses.dataclass
class Heard:
    """One robot's input: what is kept for its bag and the scans not yet taken."""

    kept: BagMessages = dataclasses.field(default_factory=BagMessages)
    pending: list[tuple] = dataclasses.field(default_factory=list)
    odom_frame: str = ""
    first_odom: tuple[float, float, float] | None = None
    last_heard: float | None = None  # (monotonic) when its newest scan came
    layout: tuple | None = None  # its first scan's beams (count, angle_min, angle_increment): every scan's
    dropped: int = 0


class RosRobots:
    """The rclpy node of the ROS 2 robots ``cfg.ros2.namespaces`` (see the module), spun in a thread."""

    def __init__(self, cfg: RunConfig):
        rclpy = need_rclpy()
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import LaserScan

        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:  # (PyPI's ROS wheels have no tf2_msgs; a sourced ROS 2 install has)
            TFMessage = None
            log.warning("tf2_msgs is not installed: /tf_static is not read (each robot's LiDAR is taken to sit at its "
                        "odometry's child frame) and map -> odom is not published; source a ROS 2 install for both")
        self.cfg, self.s, self.rclpy = cfg, cfg.ros2, rclpy
        self.PoseStamped, self.TFMessage = PoseStamped, TFMessage
        self.names = list(self.s.namespaces)
        self.origins = self.s.poses() or [(0.0, 0.0, 0.0)] * len(self.names)
        self.topics = BagTopics(self.s.scan_topic, self.s.odom_topic)
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("swarmmap_world", context=self.context)
        sensor = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
        latched = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.heard = [Heard() for _ in self.names]
        self.static = BagMessages()  # /tf_static: the LiDARs' mounts
        self.lock = threading.Lock()
        self.told: set[str] = set()
        for i, ns in enumerate(self.names):
            self.node.create_subscription(LaserScan, f"/{ns}/{self.s.scan_topic}", lambda m, i=i: self.on_scan(m, i), sensor)
            self.node.create_subscription(Odometry, f"/{ns}/{self.s.odom_topic}", lambda m, i=i: self.on_odom(m, i), sensor)
            if TFMessage is not None:
                self.node.create_subscription(TFMessage, f"/{ns}/tf_static", self.on_static, latched)
        if TFMessage is not None:
            self.node.create_subscription(TFMessage, "/tf_static", self.on_static, latched)
        goal_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.goal_pubs = [self.node.create_publisher(PoseStamped, f"/{ns}/goal_pose", goal_qos) for ns in self.names]
        self.tf_pub = self.node.create_publisher(TFMessage, "/tf_static", latched) if TFMessage is not None else None
        self.frames: dict[int, str] = {}  # robot -> its odometry frame, once known (map -> it is published)
        self.publishers = Publishers(self.node, [f"/{ns}/{t}" for ns in self.names
                                                 for t in (self.s.scan_topic, self.s.odom_topic)])
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self.spin, name="ros2-robots", daemon=True)
        self.thread.start()
        log.info("listening on ROS 2 (ROS_DOMAIN_ID %s) for %s", os.environ.get("ROS_DOMAIN_ID", "0, the default"),
                 ", ".join(f"/{ns}/{self.s.scan_topic} + /{ns}/{self.s.odom_topic}" for ns in self.names))

    # ------------------------------------------------------------------ callbacks (the spin thread)
    def spin(self) -> None:
        while not self.closing.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.1)
                self.publishers.check(time.monotonic())
            except Exception as exc:  # (a context shut down under it: the node is closing)
                if not self.closing.is_set():
                    log.warning("ROS 2 node: %s", exc)
                return

    def on_scan(self, msg, i: int) -> None:
        with self.lock:
            h = self.heard[i]
            if len(h.kept.scans) >= self.s.max_scans:
                h.dropped += 1
                if h.dropped == 1:
                    log.warning("robot %s: %d scans heard, ros2.max_scans; its further scans are dropped and counted",
                                self.names[i], self.s.max_scans)
                return
            try:
                h.kept.add_scan(msg)
            except ValueError as exc:
                h.dropped += 1
                log.warning("robot %s: a scan refused: %s", self.names[i], exc)
                return
            scan = h.kept.scans[-1]
            layout = (len(scan[2]), scan[3], scan[4])
            if h.layout is None:
                h.layout = layout
            elif layout != h.layout:  # another sensor, or another publisher on the topic
                h.kept.scans.pop()
                h.dropped += 1
                if f"layout {i}" not in self.told:
                    self.told.add(f"layout {i}")
                    log.warning("robot %s: a scan of %d beams from %.3f rad by %.5f refused: not its first scan's beams "
                                "(%d from %.3f by %.5f); another sensor, or another publisher on the topic? Further ones are "
                                "counted", self.names[i], *layout, *h.layout)
                return
            h.pending.append(scan)
            if len(h.pending) > PENDING_MAX:
                del h.pending[0]
                h.dropped += 1
            h.last_heard = time.monotonic()

    def on_odom(self, msg, i: int) -> None:
        with self.lock:
            h = self.heard[i]
            h.kept.add_odom(msg)
            if len(h.kept.odom_t) > 10 * self.s.max_scans:  # (a bound: the oldest tenth of the odometry goes)
                cut = len(h.kept.odom_t) // 10
                del h.kept.odom_t[:cut], h.kept.odom_p[:cut]
            h.first_odom = h.first_odom or h.kept.odom_p[-1]
            frame = msg.header.frame_id.lstrip("/") or "odom"
            fresh = frame != h.odom_frame
            h.odom_frame = frame
        if fresh:
            self.frames[i] = frame
            self.publish_origins()

    def on_static(self, msg) -> None:
        with self.lock:
            self.static.add_tf(msg, True)

    # ------------------------------------------------------------------ out
    def publish_origins(self) -> None:
        """``map`` -> every known odometry frame (its ``ros2.initial_poses`` origin) on /tf_static."""
        from geometry_msgs.msg import TransformStamped

        if self.tf_pub is None:
            return

        out = []
        for i, frame in sorted(self.frames.items()):
            if frame == "map":
                continue
            x, y, yaw = self.origins[i]
            tr = TransformStamped()
            tr.header.stamp, tr.header.frame_id, tr.child_frame_id = self.node.get_clock().now().to_msg(), "map", frame
            tr.transform.translation.x, tr.transform.translation.y = float(x), float(y)
            tr.transform.rotation.z, tr.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
            out.append(tr)
        if out:
            self.tf_pub.publish(self.TFMessage(transforms=out))

    def goal(self, i: int, x: float, y: float, yaw: float) -> None:
        """Robot ``i``'s goal on ``/<ns>/goal_pose`` (frame ``map``)."""
        msg = self.PoseStamped()
        msg.header.stamp, msg.header.frame_id = self.node.get_clock().now().to_msg(), "map"
        msg.pose.position.x, msg.pose.position.y = float(x), float(y)
        msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        self.goal_pubs[i].publish(msg)

    # ------------------------------------------------------------------ scans at their poses
    def take(self, i: int) -> LaserLog | None:
        """Robot ``i``'s scans heard since the last take whose odometry has come, at their poses in the shared frame."""
        with self.lock:
            h = self.heard[i]
            if not h.pending or not h.kept.odom_t:
                return None
            newest = max(h.kept.odom_t[-50:])
            ready = [s for s in h.pending if s[0] <= newest]
            if not ready:
                return None
            h.pending = [s for s in h.pending if s[0] > newest]
            got = BagMessages(scans=ready, odom_t=h.kept.odom_t[-ODOM_KEPT:], odom_p=h.kept.odom_p[-ODOM_KEPT:],
                              odom_child=h.kept.odom_child, tf=dict(self.static.tf))
        return self.placed(i, got)

    def placed(self, i: int, got: BagMessages) -> LaserLog | None:
        ns = self.names[i]
        frame, child = got.scans[0][1], got.odom_child
        if self.tf_pub is not None and child and frame != child and f"mount {ns}" not in self.told:
            tracks = {k: PoseTrack(*v) for k, v in got.tf.items()}
            if _chain(tracks, child, frame, np.zeros(1)) is None:
                self.told.add(f"mount {ns}")
                log.warning("robot %s: no /tf_static from %s to the scans' frame %s (yet): its LiDAR is taken to sit at "
                            "its odometry's %s", ns, child, frame, child)
        try:
            placed = messages_log(f"ROS 2 /{ns}", got, True, self.topics)
        except DatasetError:
            return None  # (scans from before its first odometry)
        origin = np.asarray(self.origins[i], np.float64)
        return dataclasses.replace(placed, poses=_compose(origin[None], placed.poses), notes=[])

    def silent_for(self, i: int, now: float) -> float:
        """Seconds since robot ``i``'s newest scan (inf: none yet)."""
        last = self.heard[i].last_heard
        return math.inf if last is None else now - last

    def own_origins(self) -> list[str]:
        """The robots whose odometry began at (0, 0, 0): each its own frame, unless ``ros2.initial_poses`` says where."""
        return [ns for ns, h in zip(self.names, self.heard)
                if h.first_odom is not None and max(abs(v) for v in h.first_odom) < 1e-3]

    def close(self, run_dir: Path | None) -> None:
        """Stop listening; write what was heard (``RUN_DIR/input/<ns>/``, see the module)."""
        self.closing.set()
        self.thread.join(timeout=5)
        try:
            self.executor.shutdown()
            self.node.destroy_node()
            self.rclpy.shutdown(context=self.context)
        except Exception as exc:  # pragma: no cover - rclpy's own teardown
            log.warning("ROS 2 node: %s", exc)
        dropped = {ns: h.dropped for ns, h in zip(self.names, self.heard) if h.dropped}
        if dropped:
            log.warning("scans dropped: %s", ", ".join(f"{ns} {n}" for ns, n in sorted(dropped.items())))
        if run_dir is None:
            return
        for i, (ns, h) in enumerate(zip(self.names, self.heard)):
            if not h.kept.scans:
                continue
            out = run_dir / "input" / ns.replace("/", "_")
            try:
                placed = self.placed(i, h.kept)
                if placed is None or not len(placed):
                    raise DatasetError(f"ROS 2 /{ns}", "no scan within its odometry's time span")
                path = write_rosbag(placed, out, scan_topic="/scan", odom_topic="/odom")
                log.info("robot %s: %d scans of %d beams heard, kept in %s (poses in the shared frame)", ns, len(placed),
                         len(placed.angles), path)
            except (DatasetError, OSError) as exc:
                log.error("robot %s: what it sent could not be kept in %s: %s", ns, out, exc)


class Publishers:
    """Says, once per topic, when a topic a robot's input comes from has more than one publisher:
    DDS without its security plug-ins lets anyone on the domain publish there, and their scans
    would be taken as the robot's (docs/security.md)."""

    UNKNOWN = "_NODE_NAME_UNKNOWN_"  # what DDS says of a node whose name its discovery has not brought yet
    NAMES_WAIT_S = 10.0  # how long a second publisher waits for its name before it is told of without

    def __init__(self, node, topics: list[str], every_s: float = 0.5):
        self.node, self.topics, self.every_s = node, topics, every_s
        self.told: set[str] = set()
        self.seen: dict[str, float] = {}  # topic -> when a second publisher was first seen on it
        self.checked = 0.0

    def check(self, now: float) -> None:
        if now - self.checked < self.every_s:
            return
        self.checked = now
        for topic in self.topics:
            found = self.node.get_publishers_info_by_topic(topic)
            if len(found) > 1 and topic not in self.told:
                since = self.seen.setdefault(topic, now)
                if any(p.node_name == self.UNKNOWN for p in found) and now - since < self.NAMES_WAIT_S:
                    continue  # their names come a moment after the publishers
                self.told.add(topic)
                names = sorted(f"{p.node_namespace.rstrip('/')}/{p.node_name}" for p in found)
                log.warning("%s has %d publishers (%s): every one's messages are taken as the robot's; if one is not "
                            "the robot's, stop it (ROS 2 without SROS2 cannot tell them apart)", topic, len(found),
                            ", ".join(names))


def refuse_silent(robots: RosRobots, silent: list[int], wait_s: float) -> ConfigError:
    s = robots.s
    return ConfigError(f"ros2: no LaserScan with odometry from {', '.join(f'/{robots.names[i]}/{s.scan_topic}' for i in silent)}"
                       f" within {wait_s:.0f} s (ros2.wait_s); is the robot publishing its scans and "
                       f"/{robots.names[silent[0]]}/{s.odom_topic}, in this ROS_DOMAIN_ID?")
