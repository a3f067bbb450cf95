"""Real LiDAR logs as datasets: CARMEN and ROS bag reading, splitting into a team, the log-odds grid."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from swarmmap.shared.world.datasets import BagTopics, DatasetError, LaserLog, carmen_angles, read_log, write_rosbag
from swarmmap.shared.world.logodds import build_logodds, logit
from swarmmap.shared.world.teams import make_team, split_team
from tests.conftest import KIT_DATA

CARMEN = KIT_DATA / "carmen"
INTEL = CARMEN / "intel-corrected.log.gz"
needs_intel = pytest.mark.skipif(not INTEL.exists(), reason="kit data ../shared/data/carmen not present")
HALF = 2.0  # the synthetic robot stands in a square room of walls at x, y = +-2 m


def room_ranges(x: float, y: float, angles: np.ndarray) -> np.ndarray:
    """Ranges from (x, y) along absolute ``angles`` to the walls of the square room."""
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (HALF - x) / c, np.where(c < 0, (-HALF - x) / c, np.inf))
        ty = np.where(s > 0, (HALF - y) / s, np.where(s < 0, (-HALF - y) / s, np.inf))
    return np.minimum(tx, ty)


def synthetic_poses(n: int = 12) -> np.ndarray:
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.stack([0.8 * np.cos(t), 0.5 * np.sin(t), t + 0.3], axis=1)


def write_carmen(path: Path, beams: int = 180, n: int = 12, odom_shift: float = 0.0, gz: bool = False) -> np.ndarray:
    poses = synthetic_poses(n)
    lines = ["# message formats defined: PARAM SYNC ODOM FLASER", "PARAM robot_front_laser_max 80.0 nohost 0"]
    for k, (x, y, th) in enumerate(poses):
        r = room_ranges(x, y, th + carmen_angles(beams))
        r[::17] = 81.83  # some beams see nothing: the scanner's no-return value
        lines.append(f"ODOM {x:.6f} {y:.6f} {th:.6f} 0 0 0 {k * 0.2:.3f} nohost {k * 0.2:.3f}")
        lines.append(f"FLASER {beams} " + " ".join(f"{v:.4f}" for v in r)
                     + f" {x:.6f} {y:.6f} {th:.6f} {x + odom_shift:.6f} {y:.6f} {th:.6f} {k * 0.2 + 0.1:.3f} nohost 0")
    text = "\n".join(lines) + "\n"
    if gz:
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return poses


def on_walls(log: LaserLog) -> float:
    """The largest distance of a hit from the room's walls."""
    ranges, hit, _ = log.hits(10.0)
    a = log.poses[:, 2:3] + log.angles[None, :]
    x = log.poses[:, 0:1] + ranges * np.cos(a)
    y = log.poses[:, 1:2] + ranges * np.sin(a)
    return float(np.abs(np.maximum(np.abs(x), np.abs(y)) - HALF)[hit].max())


@pytest.mark.parametrize("beams", [180, 181, 361, 200])
@pytest.mark.parametrize("gz", [False, True])
def test_carmen_log_reads_back_its_geometry(tmp_path, beams, gz):
    path = tmp_path / ("room.log.gz" if gz else "room.clf")
    poses = write_carmen(path, beams, gz=gz)
    log = read_log(path)
    assert log.ranges.shape == (12, beams) and np.allclose(log.poses, poses, atol=1e-6)
    assert log.angles[0] == pytest.approx(-math.pi / 2)  # the first beam looks right of the heading
    assert log.no_return_m == pytest.approx(81.83)
    assert on_walls(log) < 1e-3  # every hit lies on a wall: the beams' angles are the log's
    _, hit, valid = log.hits(10.0)
    assert valid.all() and not hit[:, ::17].any() and hit.sum() == log.ranges.size - log.ranges[:, ::17].size


def test_carmen_angles_follow_carmen_for_the_common_counts():
    assert np.degrees(carmen_angles(180))[[0, 1, -1]] == pytest.approx([-90, -89, 89])
    assert np.degrees(carmen_angles(361))[[0, 1, -1]] == pytest.approx([-90, -89.5, 90])
    assert np.degrees(carmen_angles(360))[-1] == pytest.approx(89.5)
    assert np.degrees(carmen_angles(91))[[0, -1]] == pytest.approx([-90, 90])


def test_carmen_odometry_pose_and_robotlaser_lines(tmp_path):
    path = tmp_path / "room.log"
    write_carmen(path, odom_shift=0.5)
    assert np.allclose(read_log(path, pose="odom").poses[:, 0] - read_log(path).poses[:, 0], 0.5, atol=1e-6)
    # ROBOTLASER1: type start fov res max accuracy remission n ranges m remissions laser_pose robot_pose tv rv
    # fwd side turn timestamp host logger_timestamp
    start, res = -math.pi / 4, math.pi / 180
    angles = start + res * np.arange(91)
    rows = []
    for k, (x, y, th) in enumerate(synthetic_poses(5)):
        r = room_ranges(x, y, th + angles)
        rows.append(f"ROBOTLASER1 0 {start} {math.pi / 2} {res} 30.0 0.01 0 91 " + " ".join(f"{v:.4f}" for v in r)
                    + f" 0 {x} {y} {th} {x} {y} {th} 0 0 0 0 0 {k * 0.5} nohost {k * 0.5}")
    (tmp_path / "rl.log").write_text("\n".join(rows) + "\n")
    log = read_log(tmp_path / "rl.log")
    assert log.ranges.shape == (5, 91) and log.no_return_m == 30.0 and log.angles[0] == pytest.approx(start)
    assert on_walls(log) < 1e-3


def test_bad_logs_are_refused_naming_the_file_and_line(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        read_log(tmp_path / "missing.log")
    (tmp_path / "odom.log").write_text("ODOM 0 0 0 0 0 0 0 nohost 0\n")
    with pytest.raises(DatasetError, match="no FLASER or ROBOTLASER1"):
        read_log(tmp_path / "odom.log")
    path = tmp_path / "cut.log"
    write_carmen(path)
    path.write_text(path.read_text() + "FLASER 180 1.0 2.0\n")  # a half-written last line
    with pytest.raises(DatasetError, match=r"cut.log: line 27: a FLASER line that cannot be read"):
        read_log(path)
    (tmp_path / "plan.svg").write_text("<svg/>")
    with pytest.raises(DatasetError, match="not a dataset swarmmap reads"):
        read_log(tmp_path / "plan.svg")
    (tmp_path / "broken.bag").write_bytes(b"not a bag at all")
    with pytest.raises(DatasetError, match="broken.bag: cannot be read as a ROS bag"):
        read_log(tmp_path / "broken.bag")


def test_a_team_is_contiguous_segments_with_every_kth_scan_held_out(tmp_path):
    write_carmen(tmp_path / "a.log", n=40)
    write_carmen(tmp_path / "b.log", n=21)
    a, b = read_log(tmp_path / "a.log"), read_log(tmp_path / "b.log")
    team = split_team([a], 3, 5)
    scans = [np.sort(np.concatenate([r.train, r.held_out])) for r in team]
    assert np.array_equal(np.concatenate(scans), np.arange(40))  # every scan, each once, in time order
    assert [len(s) for s in scans] == [14, 13, 13]
    for r, s in zip(team, scans):
        assert np.array_equal(r.held_out, s[4::5]) and not set(r.held_out) & set(r.train)
    two = split_team([a, b], 4, 10)
    assert [r.log for r in two] == [a, a, b, b]
    with pytest.raises(DatasetError, match="give a multiple of 2"):
        split_team([a, b], 3, 10)
    with pytest.raises(DatasetError, match="cannot make 30 robots"):
        split_team([b], 30, 10)


def test_make_team_maps_the_extent_and_holds_out_labelled_beams(tmp_path):
    write_carmen(tmp_path / "room.log", n=40)
    log = read_log(tmp_path / "room.log")
    team = make_team([log], 2, max_range=10.0, resolution=0.05, holdout_every=4, margin=0.5, samples_per_beam=30,
                     occupied_depth=0.03, val_beams=60)
    x0, y0 = team.origin
    assert x0 == pytest.approx(-2.5, abs=0.01) and y0 == pytest.approx(-2.5, abs=0.01) and 100 <= min(team.shape) <= max(team.shape) <= 101
    occupied = team.val_points[team.val_labels == 1]
    assert np.abs(np.maximum(*np.abs(occupied).T) - HALF - 0.03).max() < 0.03  # just behind a wall
    free = team.val_points[team.val_labels == 0]
    assert np.abs(free).max() < HALF  # free samples lie inside the room
    # The reference: free where a scan saw through, occupied on the walls, 0.5 off the map.
    p = team.reference.probability()
    x, y, th = log.poses[0]
    ahead = np.array([[x + d * math.cos(th), y + d * math.sin(th)] for d in (0.3, 0.6)])  # seen by the first scan
    assert (team.reference.at(ahead) < 0.2).all() and team.reference.at(np.array([[50.0, 0.0]]))[0] == 0.5
    for normal in ([1.0, 0.0], [0.0, -1.0]):  # a wall's cells (a hit lands in the cell on either side of its line)
        across = np.array([(HALF + d) * np.array(normal) for d in (-0.04, -0.01, 0.01, 0.04)])
        assert team.reference.at(across).max() > 0.9
    assert p.max() == pytest.approx(0.971, abs=1e-3)
    k, scan_t, pose = 3, team.time(1, 3), team.scan(1, 3)[1]
    assert scan_t == pytest.approx(log.t[team.robots[1].train[k]] - log.t[team.robots[1].train[0]])
    assert np.allclose(pose, log.poses[team.robots[1].train[k]])


def test_a_beam_with_no_return_is_free_only_as_far_as_its_sensor_sees_and_a_given_extent_is_the_map(tmp_path):
    write_carmen(tmp_path / "room.log", n=12)
    log = read_log(tmp_path / "room.log")
    short = LaserLog(source="short", t=log.t, poses=log.poses, angles=log.angles, ranges=np.minimum(log.ranges, 3.5),
                     no_return_m=3.5)  # a 3.5 m scanner: no return at 3.5 m
    ranges, hit, _ = short.hits(10.0)
    assert not hit[short.ranges >= 3.5].any() and ranges[~hit].max() == pytest.approx(3.5) and short.reach(10.0) == 3.5
    ranges, hit, _ = log.hits(10.0)  # a SICK log's 81.83 m no-return value: free to world.lidar_max_range_m
    assert ranges[~hit].max() == pytest.approx(10.0) and log.reach(10.0) == 10.0
    team = make_team([log], 1, max_range=10.0, resolution=0.1, holdout_every=4, margin=0.5, samples_per_beam=10,
                     occupied_depth=0.03, val_beams=30, extent=(-5.0, -3.0, 7.0, 3.0))
    assert team.origin == (-5.0, -3.0) and team.shape == (60, 120)


def test_log_odds_grid_counts_each_cell_once_per_beam():
    grid = build_logodds((10, 40), (0.0, 0.0), 0.1, np.array([[0.05, 0.05]]), np.array([[0.0, 0.0, 0.0]]),
                         np.array([[2.0, 2.0, 3.5]]), np.array([[True, True, False]]))
    row = grid.logodds[0]
    assert row[20] == pytest.approx(2 * logit(0.7) + logit(0.4))  # two beams ended in cell 20, the third crossed it
    assert row[5] == pytest.approx(max(3 * logit(0.4), logit(0.1192)))  # crossed by three beams, clamped
    assert row[25] == pytest.approx(logit(0.4))  # only the no-hit beam, free up to its range
    assert row[36] == 0 and (grid.logodds[1:] == 0).all()  # never reached


def rooms_bag(tmp_path: Path, storage: str) -> tuple[LaserLog, Path]:
    write_carmen(tmp_path / "room.log", n=20)
    log = read_log(tmp_path / "room.log")
    return log, write_rosbag(log, tmp_path / f"bag-{storage}", storage=storage)


def same_scans(a: LaserLog, b: LaserLog) -> None:
    assert a.ranges.shape == b.ranges.shape
    assert np.allclose(a.poses[:, :2], b.poses[:, :2], atol=1e-6)
    assert np.allclose(np.angle(np.exp(1j * (a.poses[:, 2] - b.poses[:, 2]))), 0, atol=1e-6)
    assert np.allclose(a.angles, b.angles, atol=1e-6) and np.allclose(a.ranges, b.ranges, atol=1e-4)
    assert np.array_equal(a.hits(10.0)[1], b.hits(10.0)[1])


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag2_of_a_log_reads_back_the_same_scans(tmp_path, storage):
    log, bag = rooms_bag(tmp_path, storage)
    back = read_log(bag)
    same_scans(log, back)
    assert back.notes == ["poses from odometry /odom"]
    if storage == "mcap":  # the bare .mcap file too
        same_scans(log, read_log(next(bag.glob("*.mcap"))))
    with pytest.raises(DatasetError, match=r"no scan topic '/base_scan' \(LaserScan topics in it: \['/scan'\]\)"):
        read_log(bag, topics=BagTopics(scan="/base_scan"))
    with pytest.raises(FileExistsError):
        write_rosbag(log, bag)


def test_tf_poses_chain_map_odom_base_and_laser(tmp_path):
    """A bag without odometry: the scans' poses from tf (map -> odom -> base_link, and a static
    base_link -> laser 0.2 m ahead), interpolated at each scan's stamp."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from swarmmap.shared.world.datasets import ros_time

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    poses = synthetic_poses(10)  # the laser's, as wanted

    def tf(parent, child, x, y, th, t):
        return T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=ros_time(t), frame_id=parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))))

    angles = carmen_angles(90)
    with Writer(tmp_path / "tf-bag", version=9) as w:
        c_tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_static = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_scan = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        w.write(c_static, 1, ts.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[tf("base_link", "laser", 0.2, 0, 0, 0)]),
                                               "tf2_msgs/msg/TFMessage"))
        for k, (x, y, th) in enumerate(poses):
            t = 10.0 + k
            # the base stands 0.2 m behind the laser; odom is 1 m east of map
            bx, by = x - 0.2 * math.cos(th), y - 0.2 * math.sin(th)
            msg = T["tf2_msgs/msg/TFMessage"](transforms=[tf("map", "odom", 1.0, 0, 0, t), tf("odom", "base_link", bx - 1.0, by, th, t)])
            w.write(c_tf, int(t * 1e9), ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
            if 0 < k < len(poses) - 1:  # scans inside the poses' span, half-way between two of them
                pass
        for k in range(len(poses)):
            t = 10.0 + k
            scan = T["sensor_msgs/msg/LaserScan"](
                header=T["std_msgs/msg/Header"](stamp=ros_time(t), frame_id="laser"), angle_min=float(angles[0]),
                angle_max=float(angles[-1]), angle_increment=float(angles[1] - angles[0]), time_increment=0.0, scan_time=0.0,
                range_min=0.1, range_max=30.0,
                ranges=room_ranges(*poses[k, :2], poses[k, 2] + angles).astype(np.float32), intensities=np.zeros(0, np.float32))
            w.write(c_scan, int(t * 1e9), ts.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
        late = T["sensor_msgs/msg/LaserScan"](
            header=T["std_msgs/msg/Header"](stamp=ros_time(99.0), frame_id="laser"), angle_min=float(angles[0]),
            angle_max=float(angles[-1]), angle_increment=float(angles[1] - angles[0]), time_increment=0.0, scan_time=0.0,
            range_min=0.1, range_max=30.0, ranges=np.full(90, np.inf, np.float32), intensities=np.zeros(0, np.float32))
        w.write(c_scan, int(99e9), ts.serialize_cdr(late, "sensor_msgs/msg/LaserScan"))
    log = read_log(tmp_path / "tf-bag")
    assert len(log) == 10 and "left out 1 scans outside the poses' time span" in log.notes
    assert np.allclose(log.poses[:, :2], poses[:, :2], atol=1e-6)
    assert np.allclose(np.angle(np.exp(1j * (log.poses[:, 2] - poses[:, 2]))), 0, atol=1e-6)
    assert on_walls(log) < 1e-3
    with pytest.raises(DatasetError, match="tf has no chain from 'world'"):
        read_log(tmp_path / "tf-bag", topics=BagTopics(fixed_frame="world"))


def test_ros1_bag_reads(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    poses = synthetic_poses(6)
    angles = carmen_angles(181)
    with Writer(tmp_path / "run.bag") as w:
        c_scan = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        c_odom = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        for k, (x, y, th) in enumerate(poses):
            stamp = T["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=0)
            header = T["std_msgs/msg/Header"](seq=k, stamp=stamp, frame_id="laser")
            scan = T["sensor_msgs/msg/LaserScan"](header=header, angle_min=float(angles[0]), angle_max=float(angles[-1]),
                                                  angle_increment=float(angles[1] - angles[0]), time_increment=0.0,
                                                  scan_time=0.0, range_min=0.1, range_max=30.0,
                                                  ranges=room_ranges(x, y, th + angles).astype(np.float32),
                                                  intensities=np.zeros(0, np.float32))
            w.write(c_scan, (100 + k) * 10**9, ts.serialize_ros1(scan, "sensor_msgs/msg/LaserScan"))
            pose = T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                                 orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2),
                                                                                               w=math.cos(th / 2))),
                covariance=np.zeros(36))
            v = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            twist = T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=v, angular=v),
                                                               covariance=np.zeros(36))
            odom = T["nav_msgs/msg/Odometry"](header=header, child_frame_id="laser", pose=pose, twist=twist)
            w.write(c_odom, (100 + k) * 10**9, ts.serialize_ros1(odom, "nav_msgs/msg/Odometry"))
    log = read_log(tmp_path / "run.bag")
    assert log.ranges.shape == (6, 181) and np.allclose(log.poses[:, :2], poses[:, :2], atol=1e-6)
    assert on_walls(log) < 1e-3


@needs_intel
def test_intel_log_walls_are_sharp_with_carmens_beam_order():
    """The Intel log read as CARMEN lays its beams out (right to left) puts the hits of hundreds of
    scans onto few cells (crisp walls); beams read the other way round smear them."""
    log = read_log(INTEL)
    assert log.ranges.shape == (910, 180) and log.no_return_m == pytest.approx(81.83)

    def hit_cells(angles: np.ndarray) -> int:
        ranges, hit, _ = log.hits(10.0)
        a = log.poses[:, 2:3] + angles[None, :]
        x, y = log.poses[:, 0:1] + ranges * np.cos(a), log.poses[:, 1:2] + ranges * np.sin(a)
        return len(np.unique(np.stack([np.floor(x[hit] / 0.05), np.floor(y[hit] / 0.05)], 1), axis=0))

    assert hit_cells(log.angles) < 0.6 * hit_cells(log.angles[::-1])


def test_a_dataset_run_takes_the_dataset_defaults_under_what_the_user_gives():
    from swarmmap.shared.run.config import resolve

    cfg = resolve({"world": {"dataset": "x.log"}}, preset="demo", environ={})
    assert cfg.world.dataset == ["x.log"] and cfg.world.lidar_max_range_m == 10.0
    assert cfg.lidar.range_noise_std_m == 0 and cfg.lidar.dropout_prob == 0  # real data: nothing added
    cfg = resolve({"world": {"dataset": ["x.log"], "lidar_max_range_m": 6.0}, "lidar": {"dropout_prob": 0.1}},
                  preset="demo", environ={})
    assert cfg.world.lidar_max_range_m == 6.0 and cfg.lidar.dropout_prob == 0.1 and cfg.lidar.range_noise_std_m == 0
    plain = resolve(preset="demo", environ={})
    assert plain.world.dataset == [] and plain.lidar.range_noise_std_m == 0.01 and plain.world.lidar_max_range_m == 3.5
    again = resolve(config_file=None, cli=cfg.model_dump(mode="json"), environ={})  # a run's config.yaml, read back
    assert again == cfg


def test_odometry_bag_places_the_lidar_by_tf_static_and_takes_scans_in_stamp_order(tmp_path):
    """Odometry of the base with the LiDAR mounted 0.2 m ahead and turned round (``/tf_static``
    base_link -> laser), scans written out of stamp order, one reading beyond ``range_max`` (a
    driver's error code): the scans land on the walls, in time order, the bad reading dropped."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from swarmmap.shared.world.datasets import ros_time

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    poses = synthetic_poses(10)  # the laser's
    angles = carmen_angles(90)

    def quat(th):
        return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))

    mount = T["geometry_msgs/msg/TransformStamped"](
        header=T["std_msgs/msg/Header"](stamp=ros_time(0.0), frame_id="base_link"), child_frame_id="laser",
        transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=0.2, y=0.0, z=0.0),
                                                   rotation=quat(math.pi)))
    with Writer(tmp_path / "odom-bag", version=9) as w:
        c_static = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_odom = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        c_scan = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        c_wrong = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        w.write(c_static, 1, ts.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[mount]), "tf2_msgs/msg/TFMessage"))
        for k, (x, y, th) in enumerate(poses):
            base_th = th - math.pi  # the laser looks backwards: the base faces the other way
            bx, by = x - 0.2 * math.cos(base_th), y - 0.2 * math.sin(base_th)
            header = T["std_msgs/msg/Header"](stamp=ros_time(10.0 + k), frame_id="odom")
            odom = T["nav_msgs/msg/Odometry"](
                header=header, child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=bx, y=by, z=0.0),
                                                     orientation=quat(base_th)), covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                       angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36)))
            w.write(c_odom, int((10.0 + k) * 1e9), ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))
        for k in [*range(5, 10), *range(5)]:  # written out of order
            ranges = room_ranges(*poses[k, :2], poses[k, 2] + angles).astype(np.float32)
            ranges[3] = 65.533  # beyond range_max
            scan = T["sensor_msgs/msg/LaserScan"](
                header=T["std_msgs/msg/Header"](stamp=ros_time(10.0 + k), frame_id="laser"), angle_min=float(angles[0]),
                angle_max=float(angles[-1]), angle_increment=float(angles[1] - angles[0]), time_increment=0.0,
                scan_time=0.0, range_min=0.1, range_max=30.0, ranges=ranges, intensities=np.zeros(0, np.float32))
            w.write(c_scan, int((10.0 + k) * 1e9), ts.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
        w.write(c_wrong, 1, ts.serialize_cdr(T["geometry_msgs/msg/PoseStamped"](
            header=T["std_msgs/msg/Header"](stamp=ros_time(10.0), frame_id="map"),
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                             orientation=quat(0.0))), "geometry_msgs/msg/PoseStamped"))
    log = read_log(tmp_path / "odom-bag")
    assert np.all(np.diff(log.t) > 0) and len(log) == 10
    assert np.allclose(log.poses[:, :2], poses[:, :2], atol=1e-6)
    assert np.allclose(np.angle(np.exp(1j * (log.poses[:, 2] - poses[:, 2]))), 0, atol=1e-6)
    assert np.isnan(log.ranges[:, 3]).all() and not log.hits(10.0)[2][:, 3].any()
    assert on_walls(log) < 1e-3
    with pytest.raises(DatasetError, match=r"topic '/pose' holds geometry_msgs/msg/PoseStamped, not nav_msgs/msg/Odometry"):
        read_log(tmp_path / "odom-bag", topics=BagTopics(odom="/pose"))


def test_damaged_input_is_refused_or_left_out_with_a_reason(tmp_path):
    good = tmp_path / "good.log.gz"
    write_carmen(good, n=30, gz=True)
    data = bytearray(good.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 40] = bytes(40)  # a damaged deflate stream
    (tmp_path / "damaged.log.gz").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="damaged.log.gz: cannot be read"):
        read_log(tmp_path / "damaged.log.gz")
    log = read_log(good)
    poses = log.poses.copy()
    poses[[2, 5]] = np.nan
    kept = LaserLog(source="x", t=log.t, poses=poses, angles=log.angles, ranges=log.ranges, no_return_m=log.no_return_m)
    assert len(kept) == len(log) - 2 and "left out 2 scans whose pose or stamp is not a finite number" in kept.notes
    corrupt = log.poses.copy()
    corrupt[7, 0] = 1e308  # finite, but no robot's: the map's extent would be infinite
    far = LaserLog(source="x", t=log.t, poses=corrupt, angles=log.angles, ranges=log.ranges, no_return_m=log.no_return_m)
    assert len(far) == len(log) - 1 and "left out 1 scans whose pose lies beyond 1000 km of the origin" in far.notes
    with pytest.raises(DatasetError, match="no laser scans in it"):
        LaserLog(source="x", t=log.t[:1], poses=poses[2:3], angles=log.angles, ranges=log.ranges[:1], no_return_m=80.0)


def test_stamps_headings_and_carmens_100_degree_mode():
    from types import SimpleNamespace

    from swarmmap.shared.world.datasets import _yaw, ros_time

    t = ros_time(2.9999999999)
    assert (t.sec, t.nanosec) == (3, 0)
    t = ros_time(1.25)
    assert (t.sec, t.nanosec) == (1, 250_000_000)
    assert _yaw(SimpleNamespace(x=0.0, y=0.0, z=1.0, w=1.0)) == pytest.approx(math.pi / 2)  # not normalised
    a = carmen_angles(401)
    assert math.degrees(a[0]) == pytest.approx(-50) and math.degrees(a[-1]) == pytest.approx(50)


def test_a_log_made_to_take_memory_is_refused_in_seconds_within_its_caps(tmp_path):
    """A gzipped log of one 30 MB line (about 30 KB on disk) and a FLASER line of a million beams are
    refused by name before they are read whole (they took 309 MB and 732 MB and 78 s)."""
    import resource
    import time

    from swarmmap.shared.world.datasets import MAX_BEAMS, MAX_LINE_CHARS

    (tmp_path / "one-line.log.gz").write_bytes(gzip.compress(b"FLASER " + b"1" * 30_000_000))
    assert (tmp_path / "one-line.log.gz").stat().st_size < 100_000
    (tmp_path / "wide.log").write_text(f"FLASER 1000000 {'2 ' * 1000} 0 0 0 0 0 0 0 host 0\n")
    limit = resource.getrlimit(resource.RLIMIT_AS)
    start = time.monotonic()
    try:  # address space: what this process has mapped now (torch's libraries among it) and 512 MiB more
        resource.setrlimit(resource.RLIMIT_AS, (int(_mapped_bytes() + (512 << 20)), limit[1]))
        with pytest.raises(DatasetError, match=f"line 1 is longer than {MAX_LINE_CHARS} characters"):
            read_log(tmp_path / "one-line.log.gz")
        with pytest.raises(DatasetError, match=f"line 1: a FLASER line that cannot be read .*between 0 and {MAX_BEAMS}"):
            read_log(tmp_path / "wide.log")
    finally:
        resource.setrlimit(resource.RLIMIT_AS, limit)
    assert time.monotonic() - start < 5


def _mapped_bytes() -> int:
    """This process's virtual memory now (Linux: /proc/self/statm, in pages)."""
    import os

    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def zstd_zeros(n: int) -> bytes:
    """``n`` zero bytes as one zstd frame, compressed a MiB at a time (a 1 GiB one is about 33 KB)."""
    from backports import zstd

    c = zstd.ZstdCompressor()
    return b"".join([*(c.compress(b"\0" * (1 << 20)) for _ in range(n >> 20)), c.flush()])


def mcap_with_chunk(path: Path, stated: int, records: bytes, compression: str = "zstd") -> Path:
    """A bare MCAP file: its magic, a header, one chunk of ``records`` stating ``stated`` bytes inflated, a footer."""
    import struct

    def record(op: int, content: bytes) -> bytes:
        return bytes([op]) + struct.pack("<Q", len(content)) + content

    def string(s: str) -> bytes:
        return struct.pack("<I", len(s)) + s.encode()

    chunk = struct.pack("<QQQI", 0, 1, stated, 0) + string(compression) + struct.pack("<Q", len(records)) + records
    magic = b"\x89MCAP0\r\n"
    path.write_bytes(magic + record(0x01, string("ros2") + string("x")) + record(0x06, chunk)
                     + record(0x02, struct.pack("<QQI", 0, 0, 0)) + magic)
    return path


@pytest.mark.parametrize("stated", [1 << 30, 1 << 20])
def test_an_mcap_chunk_that_inflates_to_a_gigabyte_is_refused_before_it_is_read(tmp_path, memory_limit, stated):
    """A 33 KB MCAP whose zstd chunk inflates to 1 GiB, stating so or stating 1 MiB: refused by
    name under a 512 MiB memory limit, without inflating more than the chunk's cap."""
    bomb = mcap_with_chunk(tmp_path / "bomb.mcap", stated, zstd_zeros(1 << 30))
    assert bomb.stat().st_size < 100_000
    memory_limit(512)
    with pytest.raises(DatasetError, match="refused before it is read: chunk 0 .*(states|inflates to more than)"):
        read_log(bomb)


def test_a_ros1_chunk_that_inflates_to_more_than_it_states_is_refused(tmp_path):
    """A ROS 1 bag's bz2 chunk stating 1 MiB that inflates to 16 MiB is refused by name."""
    import bz2
    import struct

    from swarmmap.shared.world.bagcheck import check_ros1

    def field(name: str, value: bytes) -> bytes:
        return struct.pack("<I", len(name) + 1 + len(value)) + name.encode() + b"=" + value

    header = field("op", b"\x05") + field("compression", b"bz2") + field("size", struct.pack("<I", 1 << 20))
    data = bz2.compress(b"\0" * (16 << 20))
    bag = tmp_path / "bomb.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n" + struct.pack("<I", len(header)) + header + struct.pack("<I", len(data)) + data)
    with pytest.raises(ValueError, match=r"chunk 0 at byte \d+ \(bz2\): it inflates to more than 1048576 bytes"):
        check_ros1(bag)
    with pytest.raises(DatasetError, match="refused before it is read"):
        read_log(bag)


def test_each_heard_scan_is_judged_by_its_own_limits_and_another_sensors_scans_are_left_out():
    """A LaserScan's readings below its own range_min or above its range_max are no measurement;
    scans of other beams than the first's (another publisher on the topic) are left out, said in
    the log's notes; one of more than MAX_BEAMS beams is refused."""
    from types import SimpleNamespace

    from swarmmap.shared.world.datasets import MAX_BEAMS, BagMessages, messages_log

    def scan(k, ranges, range_min=0.1, angle_min=-1.0):
        header = SimpleNamespace(stamp=SimpleNamespace(sec=k, nanosec=0), frame_id="laser")
        return SimpleNamespace(header=header, ranges=ranges, angle_min=angle_min, angle_increment=0.5, range_min=range_min,
                               range_max=5.0)

    def odom(k):
        pose = SimpleNamespace(position=SimpleNamespace(x=0.1 * k, y=0.0), orientation=SimpleNamespace(x=0, y=0, z=0, w=1))
        return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=k, nanosec=0), frame_id="odom"),
                               child_frame_id="laser", pose=SimpleNamespace(pose=pose))

    got = BagMessages()
    for k in range(6):
        got.add_odom(odom(k))
    got.add_scan(scan(1, [0.05, 1.0, 6.0, 2.0, 3.0]))
    got.add_scan(scan(2, [0.05, 1.0, 2.0, 2.0, 3.0], range_min=0.01))  # its own limit lets 0.05 through
    got.add_scan(scan(3, [0.01] * 7, range_min=0.0))  # another publisher: 7 beams
    got.add_scan(scan(4, [1.0] * 5, angle_min=0.0))  # other angles
    log = messages_log("test", got, True, BagTopics())
    assert log.ranges.shape == (2, 5) and any("left out 2 scans of other beams" in n for n in log.notes)
    assert np.isnan(log.ranges[0, 0]) and np.isnan(log.ranges[0, 2]) and log.ranges[1, 0] == pytest.approx(0.05)
    with pytest.raises(ValueError, match="beams"):
        got.add_scan(scan(5, [1.0] * (MAX_BEAMS + 1)))
