"""Two ROS 2 robots for the tests, played by a real rclpy peer in its own process: it simulates a
two-room building of its own (wall segments, a LiDAR cast against them) and drives each robot to
every goal it receives on ``/<ns>/goal_pose`` along a shortest path on its own map, as a Nav2
robot would.

    python -m tests.e2e.ros2_robots drive OUT.json NS_A NS_B   # until SIGTERM
    python -m tests.e2e.ros2_robots listen OUT.json             # the maps a late subscriber gets, then exits

``drive`` publishes, per robot, ``/<ns>/scan`` (LaserScan, 180 beams, 3.5 m, 10 Hz, frame
``<ns>/base_scan``), ``/<ns>/odom`` (Odometry in the robot's own frame ``<ns>/odom``, which starts at
(0, 0, 0): the robot's start in the building is :data:`STARTS`) and the LiDAR's mount on
``/tf_static`` (``<ns>/base_footprint`` -> ``<ns>/base_scan``, 0.1 m ahead; where tf2_msgs is not
installed, the LiDAR is the base and there is no tf); a stranger node holds a publisher on the
first robot's scan topic. It rewrites OUT.json every half second: the goals received, the scans
published (and those of them sent while a subscriber was matched), metres driven, the share of the
building's free space its beams have crossed over time, every OccupancyGrid received (and when),
and the transforms received on ``/tf_static``.
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import os
import signal
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

try:
    from tf2_msgs.msg import TFMessage
except ImportError:  # (PyPI's ROS wheels have no tf2_msgs: no transforms then)
    TFMessage = None

SIZE = (10.0, 6.0)  # the building: x 0-10, y 0-6 m
WALLS = np.array([  # (x0, y0, x1, y1): the outline, a wall between two rooms with a door (y 4.2-5.4), a pillar
    (0, 0, 10, 0), (10, 0, 10, 6), (10, 6, 0, 6), (0, 6, 0, 0),
    (5, 0, 5, 4.2), (5, 5.4, 5, 6),
    (7.5, 2, 8, 2), (8, 2, 8, 2.5), (8, 2.5, 7.5, 2.5), (7.5, 2.5, 7.5, 2),
], np.float64)
STARTS = [(1.5, 1.5, 0.0), (1.5, 4.5, math.pi / 2)]
MOUNT = 0.1  # the LiDAR, ahead of the base
BEAMS, RANGE, RATE, SPEED, CELL, CLEARANCE = 180, 3.5, 10.0, 0.5, 0.1, 0.2


def cast(x: float, y: float, angles: np.ndarray) -> np.ndarray:
    """Ranges from (x, y) along ``angles`` to the nearest wall (inf beyond RANGE)."""
    d = np.stack([np.cos(angles), np.sin(angles)], 1)[:, None, :]  # (B, 1, 2)
    a, b = WALLS[None, :, :2], WALLS[None, :, 2:]
    e = b - a
    denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    w = a - np.array([x, y])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / denom
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom
    t = np.where((np.abs(denom) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1), t, np.inf).min(1)
    return np.where(t < RANGE, t, np.inf)


def wall_distance(p: np.ndarray) -> np.ndarray:
    """(N,) the distance of points (N, 2) to the nearest wall."""
    a, b = WALLS[:, :2], WALLS[:, 2:]
    e = b - a
    s = np.clip(((p[:, None, :] - a) * e).sum(-1) / (e * e).sum(-1), 0, 1)
    return np.linalg.norm(p[:, None, :] - (a + s[..., None] * e), axis=-1).min(1)


class Building:
    """The building on a grid: free cells (with clearance) for paths, and the cells beams crossed."""

    def __init__(self):
        self.shape = (int(SIZE[1] / CELL), int(SIZE[0] / CELL))
        ys, xs = np.mgrid[0:self.shape[0], 0:self.shape[1]]
        self.centres = np.stack([(xs + 0.5) * CELL, (ys + 0.5) * CELL], -1).reshape(-1, 2)
        dist = wall_distance(self.centres).reshape(self.shape)
        self.drivable = dist > CLEARANCE
        self.free = dist > 0.5 * CELL * math.sqrt(2)
        self.seen = np.zeros(self.shape, bool)

    def cell(self, x: float, y: float) -> tuple[int, int]:
        return (min(max(int(y / CELL), 0), self.shape[0] - 1), min(max(int(x / CELL), 0), self.shape[1] - 1))

    def path(self, start, goal) -> list[tuple[float, float]]:
        """A shortest 8-way path of drivable cells from ``start`` to the drivable cell nearest ``goal``."""
        ok = np.argwhere(self.drivable)
        g = tuple(ok[np.argmin(np.hypot(ok[:, 0] - goal[1] / CELL, ok[:, 1] - goal[0] / CELL))])
        s = self.cell(*start)
        dist, prev, todo = {s: 0.0}, {}, [(0.0, s)]
        while todo:
            d, c = heapq.heappop(todo)
            if c == g:
                break
            if d > dist.get(c, math.inf):
                continue
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    n = (c[0] + dr, c[1] + dc)
                    if (dr or dc) and 0 <= n[0] < self.shape[0] and 0 <= n[1] < self.shape[1] and self.drivable[n]:
                        nd = d + math.hypot(dr, dc)
                        if nd < dist.get(n, math.inf):
                            dist[n], prev[n] = nd, c
                            heapq.heappush(todo, (nd, n))
        if g not in dist:
            return []
        out, c = [], g
        while c != s:
            out.append(((c[1] + 0.5) * CELL, (c[0] + 0.5) * CELL))
            c = prev[c]
        return out[::-1]

    def look(self, x: float, y: float, angles: np.ndarray, ranges: np.ndarray) -> None:
        t = np.arange(0, RANGE, CELL / 2)
        r = np.where(np.isfinite(ranges), ranges, RANGE)
        pts = np.array([x, y]) + t[None, :, None] * np.stack([np.cos(angles), np.sin(angles)], 1)[:, None, :]
        pts = pts[t[None, :] < r[:, None]]
        c = np.clip((pts / CELL).astype(int), 0, [self.shape[1] - 1, self.shape[0] - 1])
        self.seen[c[:, 1], c[:, 0]] = True

    def coverage(self) -> float:
        return float((self.seen & self.free).sum() / self.free.sum())


def stamp_of(node):
    return node.get_clock().now().to_msg()


def grid_record(msg: OccupancyGrid) -> dict:
    v = np.frombuffer(bytes(msg.data), np.int8) if not isinstance(msg.data, list) else np.array(msg.data, np.int8)
    return {"t": time.time(), "width": msg.info.width, "height": msg.info.height, "resolution": msg.info.resolution,
            "origin": [msg.info.origin.position.x, msg.info.origin.position.y], "frame": msg.header.frame_id,
            "cells": int(v.size), "min": int(v.min()), "max": int(v.max()), "unknown": int((v == -1).sum()),
            "walls": int((v == 100).sum()), "free": int((v == 0).sum())}


def subscribe_maps(node, namespaces: list[str], got: dict) -> None:
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    for topic in [*(f"/{ns}/{n}" for ns in namespaces for n in ("map", "map_std")), "/map"]:
        node.create_subscription(OccupancyGrid, topic, lambda m, t=topic: got.setdefault(t, []).append(grid_record(m)), qos)


def write(path: str, doc: dict) -> None:
    with open(path + ".tmp", "w") as f:
        json.dump(doc, f)
    os.replace(path + ".tmp", path)


def drive(out: str, namespaces: list[str]) -> None:
    rclpy.init()
    node = rclpy.create_node("swarmmap_test_robots")
    stranger = rclpy.create_node("swarmmap_test_stranger")
    stranger.create_publisher(LaserScan, f"/{namespaces[0]}/scan", 10)
    building = Building()
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pose = {ns: list(start) for ns, start in zip(namespaces, STARTS)}
    route: dict[str, list] = {ns: [] for ns in namespaces}
    doc: dict = {"goals": {ns: [] for ns in namespaces}, "driven": {ns: 0.0 for ns in namespaces}, "coverage": [],
                 "maps": {}, "tf_static": {}, "scans": {ns: 0 for ns in namespaces}, "heard": {}}

    def on_goal(msg: PoseStamped, ns: str) -> None:
        gx, gy = msg.pose.position.x, msg.pose.position.y
        doc["goals"][ns].append([time.time(), gx, gy, msg.header.frame_id])
        route[ns] = building.path(pose[ns][:2], (gx, gy))

    def on_tf(msg) -> None:
        for tr in msg.transforms:
            t = tr.transform
            doc["tf_static"][f"{tr.header.frame_id}->{tr.child_frame_id}"] = [
                t.translation.x, t.translation.y, 2 * math.atan2(t.rotation.z, t.rotation.w)]

    scans = {ns: node.create_publisher(LaserScan, f"/{ns}/scan", 10) for ns in namespaces}
    odoms = {ns: node.create_publisher(Odometry, f"/{ns}/odom", 10) for ns in namespaces}
    for ns in namespaces:
        node.create_subscription(PoseStamped, f"/{ns}/goal_pose", lambda m, ns=ns: on_goal(m, ns), 10)
    mount, base = (MOUNT, "base_footprint") if TFMessage is not None else (0.0, "base_scan")
    if TFMessage is not None:  # the LiDAR's mount, and what the team says of map -> odom
        node.create_subscription(TFMessage, "/tf_static", on_tf, latched)
        mounts = node.create_publisher(TFMessage, "/tf_static", latched)
        tfs = []
        for ns in namespaces:
            tr = TransformStamped()
            tr.header.stamp, tr.header.frame_id, tr.child_frame_id = stamp_of(node), f"{ns}/{base}", f"{ns}/base_scan"
            tr.transform.translation.x, tr.transform.rotation.w = mount, 1.0
            tfs.append(tr)
        mounts.publish(TFMessage(transforms=tfs))
    subscribe_maps(node, namespaces, doc["maps"])
    stopped: list[bool] = []
    signal.signal(signal.SIGTERM, lambda *_: stopped.append(True))
    angles_rel = np.linspace(-math.pi, math.pi, BEAMS, endpoint=False)
    tick, written = time.monotonic(), 0.0
    while not stopped:
        rclpy.spin_once(node, timeout_sec=0.01)
        now = time.monotonic()
        if now < tick:
            continue
        tick += 1 / RATE
        for k, ns in enumerate(namespaces):
            x, y, yaw = pose[ns]
            if route[ns]:  # a step along its path toward the goal
                tx, ty = route[ns][0]
                d = math.hypot(tx - x, ty - y)
                step = min(SPEED / RATE, d)
                if d > 1e-9:
                    yaw = math.atan2(ty - y, tx - x)
                    x, y = x + step * math.cos(yaw), y + step * math.sin(yaw)
                    doc["driven"][ns] += step
                if d <= SPEED / RATE:
                    route[ns].pop(0)
                pose[ns] = [x, y, yaw]
            stamp = stamp_of(node)
            sx, sy, sth = STARTS[k]
            dx, dy = x - sx, y - sy  # the pose in its own odometry frame
            ox, oy = math.cos(sth) * dx + math.sin(sth) * dy, -math.sin(sth) * dx + math.cos(sth) * dy
            oyaw = yaw - sth
            odom = Odometry()
            odom.header.stamp, odom.header.frame_id, odom.child_frame_id = stamp, f"{ns}/odom", f"{ns}/{base}"
            odom.pose.pose.position.x, odom.pose.pose.position.y = ox, oy
            odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = math.sin(oyaw / 2), math.cos(oyaw / 2)
            lx, ly = x + mount * math.cos(yaw), y + mount * math.sin(yaw)
            ranges = cast(lx, ly, yaw + angles_rel)
            building.look(lx, ly, yaw + angles_rel, ranges)
            scan = LaserScan()
            scan.header.stamp, scan.header.frame_id = stamp, f"{ns}/base_scan"
            scan.angle_min, scan.angle_increment = float(angles_rel[0]), float(angles_rel[1] - angles_rel[0])
            scan.angle_max = float(angles_rel[-1])
            scan.range_min, scan.range_max = 0.12, RANGE
            scan.ranges = [float(v) for v in ranges]
            odoms[ns].publish(odom)
            scans[ns].publish(scan)
            doc["scans"][ns] += 1
            if scans[ns].get_subscription_count():  # (someone hears it: the team, once it listens)
                doc["heard"][ns] = doc["heard"].get(ns, 0) + 1
        if now - written >= 0.5:
            written = now
            doc["coverage"].append([time.time(), building.coverage()])
            write(out, doc)
    write(out, doc)
    stranger.destroy_node()
    node.destroy_node()
    rclpy.shutdown()


def listen(out: str, namespaces: list[str], seconds: float = 20.0) -> None:
    """The maps a subscriber that joins now receives (transient local), written to ``out``."""
    rclpy.init()
    node = rclpy.create_node("swarmmap_test_late")
    got: dict = {}
    subscribe_maps(node, namespaces, got)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (all(f"/{ns}/map" in got for ns in namespaces) and "/map" in got):
        rclpy.spin_once(node, timeout_sec=0.1)
    write(out, {"maps": got})
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["drive", "listen"])
    ap.add_argument("out")
    ap.add_argument("namespaces", nargs="*", default=["robot_a", "robot_b"])
    a = ap.parse_args()
    (drive if a.mode == "drive" else listen)(a.out, a.namespaces)
