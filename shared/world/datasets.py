"""Real robots' LiDAR logs as datasets: CARMEN logs and ROS bags in, per-robot scan streams out.

A :class:`LaserLog` is one robot's 2-D scans in time order: the LiDAR's pose in the map frame,
the beams' angles relative to its heading, the ranges, and what the sensor reports when a beam
sees nothing. :func:`read_log` reads

- a CARMEN log (``.log``, ``.clf``, gzipped or not): ``FLASER`` lines (``FLASER n r_1 .. r_n x y
  theta odom_x odom_y odom_theta timestamp host logger_timestamp``; the beams span 180 degrees
  from right to left, spaced as CARMEN guesses from their number) and ``ROBOTLASER1`` lines
  (which state their own start angle, spacing and maximum range). ``pose="log"`` takes the
  line's laser pose (a corrected log's SLAM poses), ``pose="odom"`` its odometry;
- a ROS 1 bag, a rosbag2 folder (``sqlite3`` or MCAP) or a bare ``.mcap`` file holding
  ``sensor_msgs/LaserScan`` and a pose source: ``nav_msgs/Odometry`` (``pose="odom"``), ``tf``
  (``pose="tf"``: the scan's frame in the fixed frame, ``map`` when the bag has it, else
  ``odom``), or ``auto`` (odometry when the bag has the topic, else tf). Each scan takes the
  pose interpolated at its stamp; scans outside the poses' time span are left out.

:mod:`swarmmap.shared.world.teams` turns logs into a team of robots.
"""

from __future__ import annotations

import gzip
import io
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from swarmmap.shared import plugins
from swarmmap.shared.plugins import DatasetReader
from swarmmap.shared.world.bagcheck import check_chunks
from swarmmap.shared.world.floorplan import missing

if TYPE_CHECKING:
    pass


MAX_POSE_M = 1_000_000.0  # a pose farther from the map's origin than this is corrupt, not a robot's


class DatasetError(ValueError):
    """A dataset that cannot be read: the message names the file and what is wrong."""

    def __init__(self, source: str | Path, why: str):
        super().__init__(f"{source}: {why}")


@dataclass(eq=False)
class LaserLog:
    """One robot's scans in time order. ``poses`` (N, 3): the LiDAR's x, y, heading in the map
    frame; ``angles`` (B,): beam directions relative to the heading; ``ranges`` (N, B) in metres,
    NaN where a beam gave no reading; ``no_return_m``: a range at or beyond it means the beam
    saw nothing (the sensor's maximum)."""

    source: str
    t: np.ndarray
    poses: np.ndarray
    angles: np.ndarray
    ranges: np.ndarray
    no_return_m: float
    min_range_m: float = 0.0
    scan_frame: str = "laser"
    notes: list[str] = field(default_factory=list)
    _hits: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.t)
        if self.poses.shape != (n, 3) or self.ranges.shape != (n, len(self.angles)):
            raise DatasetError(self.source, f"inconsistent log: {n} stamps, poses {self.poses.shape}, ranges "
                                            f"{self.ranges.shape}, {len(self.angles)} beam angles")
        keep = np.isfinite(self.t) & np.isfinite(self.poses).all(axis=1)
        if n and not keep.all():  # a pose or stamp that is no number places nothing
            self.t, self.poses, self.ranges = self.t[keep], self.poses[keep], self.ranges[keep]
            self.notes = [*self.notes, f"left out {n - int(keep.sum())} scans whose pose or stamp is not a finite number"]
            n = len(self.t)
        near = (np.abs(self.poses[:, :2]) <= MAX_POSE_M).all(axis=1)
        if n and not near.all():  # a corrupt pose (1e308) would make the map's extent infinite
            self.t, self.poses, self.ranges = self.t[near], self.poses[near], self.ranges[near]
            self.notes = [*self.notes, f"left out {n - int(near.sum())} scans whose pose lies beyond {MAX_POSE_M / 1000:.0f} km "
                                       "of the origin"]
            n = len(self.t)
        if n == 0:
            raise DatasetError(self.source, "no laser scans in it (with a finite pose)")

    def __len__(self) -> int:
        return len(self.t)

    def hits(self, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ranges, hit, valid) (N, B) for a sensor model cut at ``max_range``: a valid beam is one
        with a reading above the minimum range; it hits when its reading is below both the
        sensor's no-return value and ``max_range`` (else its range is the nearer of the two, no hit:
        a sensor that sees 3.5 m says nothing of the space beyond)."""
        if max_range not in self._hits:
            self._hits[max_range] = self._cut(max_range)
        return self._hits[max_range]

    def _cut(self, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r = self.ranges
        valid = np.isfinite(r) & (r > self.min_range_m)
        hit = valid & (r < self.no_return_m) & (r < max_range)
        return np.where(hit, r, self.reach(max_range)).astype(np.float32), hit, valid

    def reach(self, max_range: float) -> float:
        """How far a beam with no return is known free: ``max_range``, or the sensor's own maximum if nearer."""
        return float(min(max_range, self.no_return_m))

    def endpoints(self, max_range: float) -> np.ndarray:
        """(M, 2) where every beam that hits within ``max_range`` ends (the map's extent)."""
        ranges, hit, _ = self.hits(max_range)
        a = self.poses[:, 2:3] + self.angles[None, :]
        x = self.poses[:, 0:1] + ranges * np.cos(a)
        y = self.poses[:, 1:2] + ranges * np.sin(a)
        return np.stack([x[hit], y[hit]], axis=1)


# ----------------------------------------------------------------------------- CARMEN


def carmen_angles(beams: int) -> np.ndarray:
    """Beam angles of a CARMEN ``FLASER`` line of ``beams`` readings, with CARMEN's spacing for a
    SICK (``carmen_laser_guess_angle_increment``): from -90 degrees, one degree apart for 180/181
    beams, half a degree for 360/361, a quarter for 720/721; a quarter degree from -50 for 400/401
    (a SICK's 100 degree mode); any other count spread evenly over 180 degrees."""
    if beams in (400, 401):
        return np.radians(-50.0 + 0.25 * np.arange(beams)).astype(np.float64)
    step = {180: 1.0, 181: 1.0, 360: 0.5, 361: 0.5, 720: 0.25, 721: 0.25}.get(beams)
    step_rad = math.radians(step) if step is not None else math.pi / max(beams - 1, 1)
    return (-math.pi / 2 + step_rad * np.arange(beams)).astype(np.float64)


def _open_text(path: Path) -> io.TextIOBase:
    with open(path, "rb") as f:
        gz = f.read(2) == b"\x1f\x8b"
    return gzip.open(path, "rt", errors="replace") if gz else open(path, errors="replace")


def pile_up(ranges: np.ndarray) -> float:
    """The no-return reading of a log: its largest reading when many beams report it (SICK
    scanners report 50, 80 or 81.9 m for a beam that saw nothing), else infinity."""
    finite = ranges[np.isfinite(ranges)]
    if not len(finite):
        return math.inf
    top = float(finite.max())
    at_top = int((finite >= top - 1e-3).sum())
    return top if at_top >= max(3, len(finite) // 1000) else math.inf


# What a CARMEN log may hold before it is refused (a line of 1081 beams is about 10 KB; the Intel
# log holds 13,631 scans): caps that keep a crafted file from taking gigabytes and minutes.
MAX_LINE_CHARS = 1 << 20
MAX_BEAMS = 20_000
MAX_SCANS = 2_000_000


def beams(field: str) -> int:
    """A scan's count of beams (or remission values), at most MAX_BEAMS (a ValueError past it)."""
    n = int(field)
    if not 0 <= n <= MAX_BEAMS:
        raise ValueError(f"{n} beams: a scan has between 0 and {MAX_BEAMS}")
    return n


def _bounded_lines(f: io.TextIOBase, path: Path):
    """(line number, line) of a text file, refusing a line longer than MAX_LINE_CHARS before it is read whole."""
    lineno = 0
    while line := f.readline(MAX_LINE_CHARS + 1):
        lineno += 1
        if len(line) > MAX_LINE_CHARS:
            raise DatasetError(path, f"line {lineno} is longer than {MAX_LINE_CHARS} characters: not a CARMEN log line")
        yield lineno, line


def read_carmen(path: str | Path, pose: str = "log") -> LaserLog:
    """The front laser's scans of a CARMEN log (FLASER or ROBOTLASER1 lines, whichever it has;
    FLASER when both). Readings at the log's no-return value (a ROBOTLASER1 line's maximum range,
    else :func:`pile_up`) count as no return."""
    path = Path(path)
    if pose not in ("log", "odom"):
        raise DatasetError(path, f"pose {pose!r}: a CARMEN log gives 'log' (the laser line's pose) or 'odom'")
    rows: dict[str, list] = {"FLASER": [], "ROBOTLASER1": []}
    angles_of: dict[str, np.ndarray] = {}
    no_return: float | None = None
    try:
        with _open_text(path) as f:
            for lineno, line in _bounded_lines(f, path):
                kind, _, rest = line.partition(" ")
                if kind not in rows:
                    continue
                if len(rows[kind]) >= MAX_SCANS:
                    raise DatasetError(path, f"more than {MAX_SCANS} {kind} scans: split the log")
                parts = rest.split()
                try:
                    if kind == "FLASER":
                        n = beams(parts[0])
                        ranges = [float(v) for v in parts[1 : 1 + n]]
                        tail = [float(v) for v in parts[1 + n : 1 + n + 7]]
                        if len(ranges) != n or len(tail) != 7:
                            raise ValueError("too few fields")
                        laser, odom, stamp = tail[0:3], tail[3:6], tail[6]
                        beam_angles = angles_of.setdefault(f"F{n}", carmen_angles(n))
                    else:  # ROBOTLASER1 type start fov res max_range accuracy remission_mode n r.. m rem.. laser_pose robot_pose ...
                        start, res, max_r = float(parts[1]), float(parts[3]), float(parts[4])
                        n = beams(parts[7])
                        ranges = [float(v) for v in parts[8 : 8 + n]]
                        m = beams(parts[8 + n])
                        tail = [float(v) for v in parts[9 + n + m : 9 + n + m + 6]]
                        stamp = float(parts[9 + n + m + 11])
                        if len(ranges) != n or len(tail) != 6:
                            raise ValueError("too few fields")
                        laser, odom = tail[0:3], tail[3:6]
                        beam_angles = angles_of.setdefault(f"R{n} {start} {res}", start + res * np.arange(n))
                        no_return = max_r
                except (ValueError, IndexError) as exc:
                    raise DatasetError(path, f"line {lineno}: a {kind} line that cannot be read ({exc})") from None
                rows[kind].append((stamp, laser if pose == "log" else odom, ranges, beam_angles))
    except (OSError, EOFError, gzip.BadGzipFile, zlib.error) as exc:  # zlib: a damaged gzip stream
        raise DatasetError(path, f"cannot be read: {type(exc).__name__}: {exc}") from None
    kind = "FLASER" if rows["FLASER"] else "ROBOTLASER1"
    scans = rows[kind]
    if not scans:
        raise DatasetError(path, "no FLASER or ROBOTLASER1 lines: not a CARMEN laser log")
    widths = {len(s[2]) for s in scans}
    if len(widths) > 1:
        common = max(widths, key=lambda w: sum(len(s[2]) == w for s in scans))
        scans = [s for s in scans if len(s[2]) == common]
    notes = [] if len(widths) == 1 else [f"kept the {len(scans)} scans of {len(scans[0][2])} beams (the log mixes {sorted(widths)})"]
    ranges = np.array([s[2] for s in scans], np.float64)
    if kind == "FLASER" or no_return is None:
        no_return = pile_up(ranges)
    t = np.array([s[0] for s in scans], np.float64)
    if len(t) > 1 and not (np.all(np.diff(t) >= 0) and len(np.unique(t)) >= 0.9 * len(t)):  # too coarse to pace the scans
        notes.append("its timestamps do not increase scan by scan: scans served in the log's order, 0.2 s apart")
        t = 0.2 * np.arange(len(t))
    return LaserLog(source=str(path), t=t,
                    poses=np.array([s[1] for s in scans], np.float64), angles=np.asarray(scans[0][3], np.float64),
                    ranges=ranges, no_return_m=no_return, notes=notes)


# ----------------------------------------------------------------------------- ROS bags


def _yaw(q) -> float:
    """The heading of quaternion ``q`` (normalised or not)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), q.w * q.w + q.x * q.x - q.y * q.y - q.z * q.z)


def _stamp(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose ``b`` (x, y, yaw; (..., 3)) given in the frame of pose ``a``, in ``a``'s parent frame."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     np.arctan2(np.sin(a[..., 2] + b[..., 2]), np.cos(a[..., 2] + b[..., 2]))], axis=-1)


class PoseTrack:
    """Planar poses over time; :meth:`at` interpolates (x, y linearly, yaw along the short arc)."""

    def __init__(self, t: list[float], poses: list[tuple[float, float, float]], static: bool = False):
        order = np.argsort(t, kind="stable")
        self.t = np.asarray(t, np.float64)[order]
        self.poses = np.asarray(poses, np.float64).reshape(-1, 3)[order]
        self.static = static

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses (N, 3) at times ``t`` and a mask of the times the track covers."""
        t = np.asarray(t, np.float64)
        if self.static or len(self.t) == 1:
            return np.repeat(self.poses[-1:], len(t), 0), np.ones(len(t), bool)
        inside = (t >= self.t[0]) & (t <= self.t[-1])
        x = np.interp(t, self.t, self.poses[:, 0])
        y = np.interp(t, self.t, self.poses[:, 1])
        yaw = np.unwrap(self.poses[:, 2])
        th = np.interp(t, self.t, yaw)
        return np.stack([x, y, np.arctan2(np.sin(th), np.cos(th))], axis=1), inside


@dataclass
class BagTopics:
    """Where a bag's scans and poses are: ``scan`` topic, ``odom`` topic, the fixed frame of tf
    lookups (None: ``map`` when the bag has it, else ``odom``)."""

    scan: str = "/scan"
    odom: str = "/odom"
    fixed_frame: str | None = None


@dataclass
class BagMessages:
    """What :func:`read_bag` takes from a bag: scans (stamp, frame, ranges, angle_min,
    angle_increment, range_min, range_max), odometry and tf tracks."""

    scans: list[tuple] = field(default_factory=list)
    odom_t: list[float] = field(default_factory=list)
    odom_p: list[tuple[float, float, float]] = field(default_factory=list)
    odom_child: str = ""
    tf: dict[tuple[str, str], tuple[list, list, bool]] = field(default_factory=dict)

    def add_scan(self, msg) -> None:
        ranges = np.asarray(msg.ranges, np.float64)
        if len(ranges) > MAX_BEAMS:
            raise ValueError(f"a LaserScan of {len(ranges)} beams (at most {MAX_BEAMS})")
        if msg.range_max > 0:  # beyond the sensor's stated range: no measurement (a driver's error code)
            ranges[np.isfinite(ranges) & (ranges > msg.range_max)] = np.nan
        ranges[np.isfinite(ranges) & (ranges < max(float(msg.range_min), 0.0))] = np.nan  # each scan by its own limits
        ranges[np.isposinf(ranges)] = float(msg.range_max)  # REP 117: +inf is no return within range
        self.scans.append((_stamp(msg.header), msg.header.frame_id.lstrip("/"), ranges.tolist(),
                           float(msg.angle_min), float(msg.angle_increment), float(msg.range_min), float(msg.range_max)))

    def add_odom(self, msg) -> None:
        p = msg.pose.pose
        self.odom_t.append(_stamp(msg.header))
        self.odom_p.append((p.position.x, p.position.y, _yaw(p.orientation)))
        self.odom_child = (msg.child_frame_id or self.odom_child).lstrip("/")

    def add_tf(self, msg, static: bool) -> None:
        for tr in msg.transforms:
            key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
            ts, ps, _ = self.tf.setdefault(key, ([], [], static))
            ts.append(_stamp(tr.header))
            ps.append((tr.transform.translation.x, tr.transform.translation.y, _yaw(tr.transform.rotation)))


def bag_messages(path: Path, pose: str, topics: BagTopics) -> tuple[BagMessages, bool]:
    """The scans and pose messages of a bag, and whether the poses come from odometry."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:  # pragma: no cover - rosbags is a dependency
        raise DatasetError(path, "reading ROS bags needs the rosbags package (pip install rosbags)") from None
    paths = [path.parent] if path.suffix == ".mcap" and (path.parent / "metadata.yaml").exists() else [path]
    got = BagMessages()
    try:
        for p in paths:
            check_chunks(p)
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"refused before it is read: {exc}") from None
    try:
        with AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            names = {c.topic: c.msgtype for c in reader.connections}
            if topics.scan not in names:
                scans_here = sorted(t for t, m in names.items() if m.endswith("LaserScan"))
                raise DatasetError(path, f"no scan topic {topics.scan!r} (LaserScan topics in it: {scans_here or 'none'})")
            if pose == "odom" and topics.odom not in names:
                raise DatasetError(path, f"no odometry topic {topics.odom!r} (topics: {sorted(names)})")
            use_odom = pose == "odom" or (pose == "auto" and topics.odom in names)
            read = [(topics.scan, "sensor_msgs/msg/LaserScan")] + ([(topics.odom, "nav_msgs/msg/Odometry")] if use_odom else [])
            for topic, kind in read:
                if names[topic].split("/")[-1] != kind.split("/")[-1]:
                    raise DatasetError(path, f"topic {topic!r} holds {names[topic]}, not {kind}")
            # odometry: the static tf says where the LiDAR sits on the base; else the poses come from tf
            wanted = [topics.scan] + ([topics.odom, "/tf_static"] if use_odom else ["/tf", "/tf_static"])
            for conn, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic in wanted]):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == topics.scan:
                    got.add_scan(msg)
                elif conn.topic == topics.odom:
                    got.add_odom(msg)
                else:
                    got.add_tf(msg, conn.topic == "/tf_static")
    except DatasetError:
        raise
    except Exception as exc:  # rosbags raises its own errors for damaged or unknown files
        raise DatasetError(path, f"cannot be read as a ROS bag: {type(exc).__name__}: {exc}") from None
    return got, use_odom


def read_bag(path: str | Path, pose: str = "auto", topics: BagTopics | None = None) -> LaserLog:
    """The LaserScans of a ROS 1 bag, a rosbag2 folder or a ``.mcap`` file, each at its pose."""
    path, topics = Path(path), topics or BagTopics()
    if pose not in ("auto", "odom", "tf"):
        raise DatasetError(path, f"pose {pose!r}: a bag gives 'odom' (nav_msgs/Odometry), 'tf' or 'auto'")
    got, use_odom = bag_messages(path, pose, topics)
    return messages_log(str(path), got, use_odom, topics)


def messages_log(source: str, got: BagMessages, use_odom: bool, topics: BagTopics) -> LaserLog:
    """The LaserLog of a robot's scan and pose messages (from a bag, or heard live on ROS 2)."""
    path = source
    scans = got.scans
    if not scans:
        raise DatasetError(path, f"no messages on {topics.scan!r}")
    scans = [scans[k] for k in np.argsort([s[0] for s in scans], kind="stable")]  # time order, whatever the bag's
    t = np.array([s[0] for s in scans])
    frame = scans[0][1]
    tracks = {k: PoseTrack(v[0], v[1], v[2]) for k, v in got.tf.items()}
    if use_odom:
        if not got.odom_t:
            raise DatasetError(path, f"no messages on {topics.odom!r}")
        poses, inside = PoseTrack(got.odom_t, got.odom_p).at(t)
        offset = _chain(tracks, got.odom_child, frame, t)  # base -> laser, when the bag says
        if offset is not None:
            poses = _compose(poses, offset[0])
        how = f"odometry {topics.odom}"
    else:
        fixed = topics.fixed_frame or ("map" if any("map" in k for k in tracks) else "odom")
        chained = _chain(tracks, fixed, frame, t)
        if chained is None:
            raise DatasetError(path, f"tf has no chain from {fixed!r} to the scans' frame {frame!r} "
                                     f"(transforms: {sorted(f'{a}->{b}' for a, b in tracks)})")
        poses, inside = chained
        how = f"tf {fixed} -> {frame}"
    kept = [x for x, keep in zip(scans, inside) if keep]
    if not kept:
        raise DatasetError(path, f"no scan lies within the time span of its poses ({how})")
    first = kept[0]
    notes = [f"poses from {how}"]
    if len(kept) < len(scans):
        notes.append(f"left out {len(scans) - len(kept)} scans outside the poses' time span")
    alike = np.array([len(x[2]) == len(first[2]) and x[3:5] == first[3:5] for x in kept])  # one sensor's beams
    if not alike.all():
        notes.append(f"left out {int((~alike).sum())} scans of other beams than the first's ({len(first[2])} from "
                     f"{first[3]:.3f} rad by {first[4]:.5f}): another sensor, or another publisher on the topic")
        kept = [x for x, same in zip(kept, alike) if same]
    return LaserLog(source=source, t=t[inside][alike], poses=poses[inside][alike],
                    angles=first[3] + first[4] * np.arange(len(first[2])), ranges=np.array([x[2] for x in kept], np.float64),
                    min_range_m=min(x[5] for x in kept), notes=notes,  # (each scan's own range_min already applied)
                    no_return_m=first[6] if first[6] > 0 else math.inf)  # a range_max left at 0: no no-return value


def _chain(tracks: dict[tuple[str, str], PoseTrack], parent: str, child: str, t: np.ndarray):
    """The pose (N, 3) of frame ``child`` in frame ``parent`` at times ``t`` through tf's tree, and
    where every link covers the times; None when no chain joins them (identity when equal)."""
    if parent == child:
        return np.zeros((len(t), 3)), np.ones(len(t), bool)
    up: dict[str, str] = {c: p for p, c in tracks}
    path, node = [], child
    while node != parent:
        if node not in up or len(path) > 64:
            return None
        path.append((up[node], node))
        node = up[node]
    pose, inside = np.zeros((len(t), 3)), np.ones(len(t), bool)
    for link in reversed(path):
        p, ok = tracks[link].at(t)
        pose, inside = _compose(pose, p), inside & ok
    return pose, inside


# ----------------------------------------------------------------------------- any


def _is_bag(p: Path) -> bool:
    return p.is_dir() or p.name.lower().endswith((".bag", ".mcap", ".db3"))


def _is_carmen(p: Path) -> bool:
    return p.name.lower().endswith((".log", ".clf", ".log.gz", ".clf.gz", ".gz", ".txt"))


def _read_carmen(path: Path, pose: str, topics: BagTopics | None) -> LaserLog:
    return read_carmen(path, "log" if pose in ("auto", "log") else pose)


# swarmmap's own readers, registered as plug-ins (pyproject.toml's swarmmap.datasets entry points)
ROSBAG = DatasetReader(_is_bag, read_bag, "a ROS 1 bag (.bag), a rosbag2 folder or an .mcap file")
CARMEN = DatasetReader(_is_carmen, _read_carmen, "a CARMEN log (.log, .clf, gzipped or not)")


def reader_for(p: Path) -> tuple[str, DatasetReader]:
    """The installed reader that claims ``p``: one from another package before swarmmap's own (a
    package installed for a format knows it best), by name among equals."""
    readers = sorted(plugins.installed("datasets"), key=lambda r: (r.builtin, r.name))
    described, refused = [], []
    for plugin in readers:
        try:
            reader = plugins.load("datasets", plugin.name)
        except plugins.PluginError as exc:  # a broken reader keeps no other from reading
            refused.append(str(exc))
            continue
        described.append(reader.describe)
        if reader.claims(p):
            return plugin.name, reader
    give = f"give {', '.join(described[:-1])} or {described[-1]}" if len(described) > 1 else \
        f"give {described[0]}" if described else "no dataset reader is installed"
    raise DatasetError(p, f"not a dataset swarmmap reads: {give}" + "".join(f"; refused: {r}" for r in refused))


def read_log(path: str | Path, pose: str = "auto", topics: BagTopics | None = None) -> LaserLog:
    """A real LiDAR log read by the installed reader that claims it (a CARMEN log or a ROS bag, told
    apart by its name; or a format a plug-in reads)."""
    p = Path(path)
    if not p.exists():
        raise DatasetError(p, missing(p, "no such file or folder:"))
    name, reader = reader_for(p)
    got = reader.read(p, pose, topics)
    if not isinstance(got, LaserLog):
        raise DatasetError(p, str(plugins.broken_contract(name, "datasets", f"its read returned a {type(got).__name__}, "
                                                                           "not a LaserLog")))
    if (where := plugins.origin("datasets", name)) is not None:
        got.notes = [f"read by the {name} reader of {where}", *got.notes]
    return got


# ----------------------------------------------------------------------------- writing bags


def ros_time(t: float):
    """A builtin_interfaces/Time for ``t`` seconds."""
    from rosbags.typesys.stores.ros2_humble import builtin_interfaces__msg__Time as Time

    sec, nanosec = divmod(int(round(t * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def write_rosbag(log: LaserLog, out: str | Path, *, storage: str = "mcap", scan_topic: str = "/scan",
                 odom_topic: str = "/odom", start: float = 1.0) -> Path:
    """``log`` as a rosbag2 folder ``out`` (``storage`` mcap or sqlite3): ``sensor_msgs/LaserScan``
    on ``scan_topic`` in frame ``laser`` and ``nav_msgs/Odometry`` of the LiDAR's pose on
    ``odom_topic`` (frame ``odom``, child ``laser``) at every scan's stamp (``start`` + its time).
    Refuses an existing ``out``."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists: give a new folder")
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    inc = float(np.median(np.diff(log.angles))) if len(log.angles) > 1 else 0.0
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        scan_c = writer.add_connection(scan_topic, "sensor_msgs/msg/LaserScan", typestore=ts)
        odom_c = writer.add_connection(odom_topic, "nav_msgs/msg/Odometry", typestore=ts)
        range_max = log.no_return_m if math.isfinite(log.no_return_m) else float(np.nanmax(log.ranges))
        for k in range(len(log)):
            stamp = ros_time(start + float(log.t[k] - log.t[0]))
            ns = stamp.sec * 1_000_000_000 + stamp.nanosec
            ranges = np.nan_to_num(log.ranges[k], nan=0.0).astype(np.float32)
            scan = T["sensor_msgs/msg/LaserScan"](
                header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=log.scan_frame), angle_min=float(log.angles[0]),
                angle_max=float(log.angles[-1]), angle_increment=inc, time_increment=0.0, scan_time=0.0,
                range_min=float(log.min_range_m), range_max=float(range_max), ranges=ranges,
                intensities=np.zeros(0, np.float32))
            writer.write(scan_c, ns, ts.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
            x, y, th = (float(v) for v in log.poses[k])
            pose = T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                                 orientation=T["geometry_msgs/msg/Quaternion"](
                                                     x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))),
                covariance=np.zeros(36))
            twist = T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                   angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36))
            odom = T["nav_msgs/msg/Odometry"](header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="odom"),
                                              child_frame_id=log.scan_frame, pose=pose, twist=twist)
            writer.write(odom_c, ns, ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))
    return out
