"""A run in ROS terms: OccupancyGrid values, LaserScan layout and the MCAP bag."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmmap.shared.run.rosmaps import ros_occupancy, seen_cells
from swarmmap.shared.run.rosout import McapBag, grid_values, scan_arrays, trinary_values


def test_grid_values_are_percent_row_major_from_the_south_west():
    v = np.array([[0.0, 0.504, 1.2], [np.nan, 0.25, -0.1]])
    assert grid_values(v).tolist() == [0, 50, 100, -1, 25, 0]
    assert grid_values(np.array([[0.125, 0.3]]), scale=0.25).tolist() == [50, 100]  # a std on the scale of std_max
    assert trinary_values(np.array([[0, 1, 2]], np.uint8)).tolist() == [0, 100, -1]


def test_published_maps_follow_ros_conventions_walls_100_and_unknown_minus_1():
    mean = np.array([[0.9, 0.65, 0.4], [0.1, 0.196, np.nan]])
    seen = np.array([[True, True, True], [True, False, True]])
    assert ros_occupancy(mean, None, None, 0.2).tolist() == [100, 100, 40, 0, 0, -1]
    assert ros_occupancy(mean, None, seen, 0.2).tolist() == [100, 100, 40, 0, -1, -1]  # no beam went there
    std = np.array([[0.05, 0.3, 0.0], [0.0, 0.0, 0.0]])
    assert ros_occupancy(mean, std, seen, 0.2).tolist() == [100, -1, 40, 0, -1, -1]  # the model is unsure there


def test_the_cells_a_scan_saw_are_those_its_beams_crossed_and_ended_in():
    # a 1 m x 1 m grid of 0.1 m cells from (0, 0); one beam east from (0.05, 0.55) ending at 0.5 m, one north ending at 0.3 m
    seen = seen_cells((10, 10), (0.0, 0.0), 0.1, (0.05, 0.55, 0.0), np.array([0.0, math.pi / 2]), np.array([0.5, 0.3]))
    assert seen[5, :6].all() and not seen[5, 7:].any()  # along the first, to its end's cell
    assert seen[5:9, 0].all() and not seen[9, 0]  # along the second
    assert seen.sum() == 6 + 3


def test_a_scan_with_gaps_is_laid_out_evenly_relative_to_the_heading():
    yaw = 3.0
    rel = np.deg2rad(np.arange(-90, 90, 1.0))
    keep = np.ones(len(rel), bool)
    keep[[5, 6, 100]] = False  # beams that gave no reading (a real log's)
    ranges = np.linspace(1, 5, len(rel)).astype(np.float32)
    hit = np.ones(len(rel), bool)
    hit[::10] = False
    arr = scan_arrays(yaw, (yaw + rel)[keep], ranges[keep], hit[keep])
    assert arr.angle_min == pytest.approx(-math.pi / 2) and arr.angle_increment == pytest.approx(math.radians(1))
    assert len(arr.ranges) == 180 and np.isnan(arr.ranges[[5, 6, 100]]).all()
    want = np.where(hit, ranges, np.inf)
    assert np.array_equal(arr.ranges[keep], want[keep])


def test_a_bag_reads_back_with_rosbags(tmp_path):
    from rosbags.highlevel import AnyReader

    bag = McapBag(tmp_path / "bag", std_max=0.25)
    grid = np.zeros((4, 6), np.uint8)
    grid[0] = 1
    grid[3, 5] = 2
    bag.world(0.5, (-1.0, 2.0), (4, 6), grid)
    bag.scan(0, (0.5, 3.0, 0.3), 0.3 + np.linspace(-1, 1, 5), np.full(5, 2.0, np.float32), np.ones(5, bool), 3.5)
    mean = np.linspace(0, 1, 24).reshape(4, 6)
    bag.maps(0, mean, mean / 8)
    bag.maps(1, 1 - mean, None)
    counts = bag.close()
    assert counts == {"/reference": 1, "/robot_0/scan": 1, "/robot_0/pose": 1, "/tf": 1, "/robot_0/map": 1,
                      "/robot_0/map_std": 1, "/map": 2, "/robot_1/map": 1}
    with AnyReader([tmp_path / "bag"]) as reader:
        got = {}
        for conn, _, raw in reader.messages():
            got.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    assert set(got) == set(counts)
    m = got["/robot_0/map"][0]
    assert (m.info.width, m.info.height, m.info.resolution) == (6, 4, 0.5)
    assert (m.info.origin.position.x, m.info.origin.position.y, m.header.frame_id) == (-1.0, 2.0, "map")
    assert np.array_equal(m.data, grid_values(mean))
    assert np.array_equal(got["/robot_0/map_std"][0].data, grid_values(mean / 8, 0.25))
    assert np.array_equal(got["/map"][-1].data, grid_values(np.full((4, 6), 0.5)))  # the team's: the robots' mean
    assert got["/reference"][0].data.tolist()[:6] == [100] * 6 and got["/reference"][0].data[-1] == -1
    scan = got["/robot_0/scan"][0]
    assert scan.header.frame_id == "robot_0/base_scan" and scan.angle_min == pytest.approx(-1) and len(scan.ranges) == 5
    assert got["/tf"][0].transforms[0].child_frame_id == "robot_0/base_scan"
    with pytest.raises(FileExistsError):
        McapBag(tmp_path / "bag", 0.25)
