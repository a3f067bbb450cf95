"""``swarmmap ros2``: a team of ROS 2 robots. It hears their scans on ROS 2 and publishes their maps there.

Run-book: ``swarmmap ros2 --namespaces robot_a robot_b [up's options]`` (needs rclpy:
``pip install 'swarmmap[ros2]'``, or a sourced ROS 2 install).

1. An rclpy node subscribes, for every namespace, to ``/<ns>/scan`` (``sensor_msgs/LaserScan``)
   and ``/<ns>/odom`` (``nav_msgs/Odometry``: the LiDAR's pose), best effort (a sensor's QoS; a
   reliable publisher matches too). Their input is over once every robot has sent scans and none
   came for ``ros2.idle_s``; a robot that sent nothing within ``ros2.wait_s`` is refused by name.
2. Each robot's scans, at their poses, are kept as a rosbag2 in the run directory
   (``RUN_DIR/input/<ns>/<ns>.mcap``: what the team learned from, replayable with ``--dataset``).
3. The team runs as ``swarmmap up --dataset`` on them, one robot per namespace, and its observer
   publishes, at every evaluation, each robot's mean map on ``/<ns>/map``, its std on
   ``/<ns>/map_std`` (a model with one; ``100 x std / observer.std_max``) and the team's on
   ``/map``: ``nav_msgs/OccupancyGrid``, frame ``map``, reliable and transient local (a node that
   starts later gets the newest map), 0-100.

The robots' poses are taken as given, so they must share one frame (a multi-robot SLAM's
``map``, or odometry of robots started at known poses of one frame): each robot's odometry in
its own frame would put its map where it started.

Training starts when the input is over (the learners train on their data offline, as DiNNO's
offline mode does); the maps are refreshed as it goes on.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.rosmaps import need_rclpy
from swarmmap.shared.world.datasets import BagMessages, BagTopics, DatasetError, messages_log, write_rosbag

log = logging.getLogger("ros2")


def hear(cfg: RunConfig, stop: threading.Event) -> dict[str, BagMessages]:
    """Every robot's scans and odometry from ROS 2, until its input is over (see the module)."""
    rclpy = need_rclpy()
    from nav_msgs.msg import Odometry
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import LaserScan

    s = cfg.ros2
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("swarmmap_input", context=context)
    qos = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
    got = {ns: BagMessages() for ns in s.namespaces}
    last: dict[str, float] = {}
    dropped: dict[str, int] = {}

    def on_scan(msg, ns: str) -> None:
        if len(got[ns].scans) >= s.max_scans:
            dropped[ns] = dropped.get(ns, 0) + 1
            if dropped[ns] == 1:
                log.warning("robot %s: %d scans heard, ros2.max_scans; its further scans are dropped and counted", ns,
                            s.max_scans)
            return
        try:
            got[ns].add_scan(msg)
        except ValueError as exc:
            dropped[ns] = dropped.get(ns, 0) + 1
            log.warning("robot %s: a scan refused: %s", ns, exc)
            return
        last[ns] = time.monotonic()

    for ns in s.namespaces:
        node.create_subscription(LaserScan, f"/{ns}/{s.scan_topic}", lambda m, ns=ns: on_scan(m, ns), qos)
        node.create_subscription(Odometry, f"/{ns}/{s.odom_topic}", lambda m, ns=ns: got[ns].add_odom(m), qos)
    log.info("listening on ROS 2 (ROS_DOMAIN_ID %s) for %s", os.environ.get("ROS_DOMAIN_ID", "0, the default"),
             ", ".join(f"/{ns}/{s.scan_topic} + /{ns}/{s.odom_topic}" for ns in s.namespaces))
    start, said = time.monotonic(), 0.0
    publishers = Publishers(node, [f"/{ns}/{t}" for ns in s.namespaces for t in (s.scan_topic, s.odom_topic)])
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            now = time.monotonic()
            publishers.check(now)
            silent = [ns for ns in s.namespaces if ns not in last]
            if not silent and now - max(last.values()) >= s.idle_s:
                break
            if now - start > s.max_input_s:
                log.warning("the input is over after %.0f s (ros2.max_input_s), though scans still come", s.max_input_s)
                break
            if silent and now - start > s.wait_s:
                raise ConfigError(f"ros2: no LaserScan from {', '.join(f'/{ns}/{s.scan_topic}' for ns in silent)} within "
                                  f"{s.wait_s:.0f} s (ros2.wait_s); is the robot publishing, in this ROS_DOMAIN_ID?")
            if now - said >= 10:
                said = now
                log.info("heard so far: %s", ", ".join(f"{ns} {len(got[ns].scans)} scans" for ns in s.namespaces))
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
    if dropped:
        log.warning("scans dropped: %s", ", ".join(f"{ns} {n}" for ns, n in sorted(dropped.items())))
    return got


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


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Hear the robots, keep their input, run the team on it publishing its maps; the exit status."""
    from swarmmap.services import up as launcher

    s = cfg.ros2
    if not s.namespaces:
        raise ConfigError("config error:\n  ros2.namespaces: name the robots' namespaces, e.g. --namespaces robot_a robot_b")
    need_rclpy()
    cfg = launcher.prepare(cfg.model_copy(update={"robots": len(s.namespaces)}))
    if (why := launcher.run_dir_problem(cfg)) is not None:
        raise ConfigError(f"config error:\n  run_dir: {why}")
    inputs = cfg.run_dir / "input"
    if inputs.exists() and any(inputs.iterdir()):
        raise ConfigError(f"config error:\n  run_dir: {inputs} holds the input of an earlier run, which is never overwritten; "
                          "choose another run directory (or replay it: swarmmap up --dataset " + f"{inputs}/*/*.mcap)")
    got = hear(cfg, stop)
    if stop.is_set():
        return 130
    paths = []
    for ns, messages in got.items():
        try:
            robot_log = messages_log(f"ROS 2 /{ns}", messages, True, BagTopics(f"/{ns}/{s.scan_topic}", f"/{ns}/{s.odom_topic}"))
        except DatasetError as exc:
            raise ConfigError(f"ros2: robot {ns}: {exc}") from None
        path = write_rosbag(robot_log, inputs / ns.replace("/", "_"), scan_topic="/scan", odom_topic="/odom")
        paths.append(str(next(Path(path).glob("*.mcap"))))
        log.info("robot %s: %d scans of %d beams kept in %s", ns, len(robot_log), len(robot_log.angles), path)
    world = cfg.world.model_copy(update={"dataset": paths, "dataset_pose": "odom"})
    cfg = cfg.model_copy(update={"world": world, "ros2": s.model_copy(update={"publish": True}),
                                 "up": cfg.up.model_copy(update={"observer": True})})
    return launcher.run(cfg, stop)
