"""A real ROS 2 peer for the tests (rclpy, its own process): it publishes a CARMEN log's scans and
odometry on two robots' namespaces, then records every nav_msgs/OccupancyGrid it receives.

    python -m tests.e2e.ros2_peer LOG OUT.json NS_A NS_B [--scans N]

Half the log's first N scans go to each namespace (``/<ns>/scan``, ``/<ns>/odom``), once every
publisher has a subscriber and a second more; then it listens to ``/<ns>/map``, ``/<ns>/map_std`` and ``/map``
(reliable, transient local) and rewrites OUT.json after every map until it is stopped (SIGTERM).
A second node of it, a stranger, holds a publisher on the first namespace's scan topic.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import time

import rclpy
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from swarmmap.shared.world.datasets import read_log


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("log")
    ap.add_argument("out")
    ap.add_argument("namespaces", nargs=2)
    ap.add_argument("--scans", type=int, default=300)
    a = ap.parse_args()
    log = read_log(a.log)
    rclpy.init()
    node = rclpy.create_node("swarmmap_test_peer")
    pubs = {ns: (node.create_publisher(LaserScan, f"/{ns}/scan", 50), node.create_publisher(Odometry, f"/{ns}/odom", 50))
            for ns in a.namespaces}
    # A stranger on the domain: a second node with a publisher on the first robot's scan topic
    # (it sends nothing; the team must name it).
    stranger = rclpy.create_node("swarmmap_test_stranger")
    stranger.create_publisher(LaserScan, f"/{a.namespaces[0]}/scan", 10)
    got: dict[str, list[dict]] = {}

    def on_map(msg: OccupancyGrid, topic: str) -> None:
        values = list(msg.data)
        got.setdefault(topic, []).append({
            "width": msg.info.width, "height": msg.info.height, "resolution": msg.info.resolution,
            "origin": [msg.info.origin.position.x, msg.info.origin.position.y], "frame": msg.header.frame_id,
            "cells": len(values), "min": min(values), "max": max(values), "known": sum(v >= 0 for v in values)})
        with open(a.out + ".tmp", "w") as f:
            json.dump({"published": published, "maps": got}, f)
        os.replace(a.out + ".tmp", a.out)

    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    for ns in [*a.namespaces, ""]:
        for name in (("map",) if not ns else ("map", "map_std")):
            topic = f"/{ns}/{name}" if ns else "/map"
            node.create_subscription(OccupancyGrid, topic, lambda m, t=topic: on_map(m, t), qos)
    published = {ns: 0 for ns in a.namespaces}
    stopped = []
    signal.signal(signal.SIGTERM, lambda *_: stopped.append(True))
    while not stopped and not all(p.get_subscription_count() for pair in pubs.values() for p in pair):
        rclpy.spin_once(node, timeout_sec=0.1)
    settle = time.monotonic() + 1.0  # discovery is two-way: the subscribers match these publishers a moment later
    while not stopped and time.monotonic() < settle:
        rclpy.spin_once(node, timeout_sec=0.1)
    half = a.scans // 2
    step = float(log.angles[1] - log.angles[0])
    for k in range(min(a.scans, len(log))):
        if stopped:
            break
        ns = a.namespaces[k // half] if k < 2 * half else a.namespaces[-1]
        t = 100.0 + 0.2 * k
        stamp = rclpy.time.Time(seconds=int(t), nanoseconds=int(round((t % 1) * 1e9))).to_msg()
        x, y, th = (float(v) for v in log.poses[k])
        odom = Odometry()
        odom.header.stamp, odom.header.frame_id, odom.child_frame_id = stamp, "odom", "laser"
        odom.pose.pose.position.x, odom.pose.pose.position.y = x, y
        odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = math.sin(th / 2), math.cos(th / 2)
        scan = LaserScan()
        scan.header.stamp, scan.header.frame_id = stamp, "laser"
        scan.angle_min, scan.angle_increment = float(log.angles[0]), step
        scan.angle_max = float(log.angles[-1])
        scan.range_min, scan.range_max = 0.0, float(log.no_return_m)
        scan.ranges = [float(v) for v in log.ranges[k]]
        pubs[ns][1].publish(odom)
        pubs[ns][0].publish(scan)
        published[ns] += 1
        rclpy.spin_once(node, timeout_sec=0.02)
    with open(a.out + ".tmp", "w") as f:
        json.dump({"published": published, "maps": got}, f)
    os.replace(a.out + ".tmp", a.out)
    while not stopped:
        rclpy.spin_once(node, timeout_sec=0.1)
    stranger.destroy_node()
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
