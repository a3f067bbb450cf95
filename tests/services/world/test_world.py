"""The pybullet world: rays against known geometry, batching, the robot, and --export."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
import trimesh
from PIL import Image

from swarmmap.services.world.robot import LIDAR_OFFSET
from swarmmap.services.world.simulation import Simulation
from swarmmap.shared.run.config import WorldSettings
from swarmmap.shared.world.floorplan import procedural
from swarmmap.shared.world.sensing import sensor_model
from tests.conftest import SWARMMAP


@pytest.fixture(scope="module")
def room_sim():
    plan = procedural(1, 1, seed=2, corridor_width=0.0)
    room = plan.rooms[0]
    cx, cy = room.centroid.coords[0]
    paths = [np.array([[cx, cy], [cx + 0.5, cy]]), np.array([[cx, cy], [cx, cy + 0.5]])]
    sim = Simulation(plan, paths, WorldSettings(lidar_beams=4, lidar_fov_deg=360.0))
    yield sim, room
    sim.close()


def test_lidar_link_sits_where_the_urdf_puts_it(room_sim):
    sim, room = room_sim
    poses = sim.poses()
    start = sim.robots[0].path[0]
    assert poses[0, :2] == pytest.approx(start + np.array([LIDAR_OFFSET[0], 0.0]), abs=1e-6)  # heading +x
    assert poses[0, 2] == pytest.approx(0.0, abs=1e-6)
    assert poses[1, 2] == pytest.approx(np.pi / 2, abs=1e-6)


def test_beams_return_known_wall_distances_within_the_noise(room_sim):
    sim, room = room_sim
    poses = sim.poses()
    angles, ranges, hit = sim.scan(poses)
    assert hit.all()
    xmin, ymin, xmax, ymax = room.bounds
    x, y = poses[0, :2]
    expected = {0.0: xmax - x, np.pi / 2: ymax - y, -np.pi: x - xmin, -np.pi / 2: y - ymin}
    for a, r in zip(angles[0], ranges[0]):
        key = min(expected, key=lambda k: abs(np.angle(np.exp(1j * (a - k)))))
        assert r == pytest.approx(expected[key], abs=1e-4)
    noisy, h, _ = sensor_model(ranges[0], hit[0], np.random.default_rng(0), noise_std=0.01, dropout_prob=0.0,
                               min_range=0.12, max_range=3.5)
    assert np.abs(noisy - ranges[0]).max() < 0.05


def test_batched_and_per_robot_rays_agree(room_sim):
    sim, _ = room_sim
    poses = sim.poses()
    angles = poses[:, 2:3] + np.linspace(-np.pi, np.pi, 90, endpoint=False)[None, :]
    a = sim.cast(poses, angles, batched=True)
    b = sim.cast(poses, angles, batched=False)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


@pytest.mark.integration
def test_export_writes_stl_png_npz_and_a_ros_map(tmp_path):
    out = tmp_path / "export"
    proc = subprocess.run([*SWARMMAP, "world", "--preset", "smoke", "--export",
                           str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    mesh = trimesh.load(out / "plan.stl")
    assert mesh.is_watertight and mesh.bounds[1][2] == pytest.approx(2.5)
    npz = np.load(out / "occupancy.npz")
    assert npz["grid"].shape == np.asarray(Image.open(out / "occupancy.png")).shape
    assert float(npz["resolution"]) == pytest.approx(0.05) and npz["origin"].shape == (2,)
    assert 0.1 < npz["grid"].mean() < 0.6
    # the same ground truth as a ROS map, read back as map_server would: free and walls as they
    # were, the space around the building unknown (and never ground truth)
    from swarmmap.shared.run.config import WorldSettings
    from swarmmap.shared.world.plans import load_floorplan

    back = load_floorplan(str(out / "map.yaml"), WorldSettings(), 0).raster
    assert back.resolution == pytest.approx(0.05) and back.origin == pytest.approx(tuple(npz["origin"]))
    np.testing.assert_array_equal(back.grid, npz["grid"])
    assert back.unknown.any() and not (back.unknown & (npz["grid"] == 0)).any()
    assert back.unknown[0].all() and back.unknown[-1].all(), "the margin around the building is unknown"


@pytest.mark.integration
def test_bad_floorplan_stops_the_world_with_its_name(tmp_path):
    bad = tmp_path / "plan.svg"
    bad.write_text("not xml at all <")
    proc = subprocess.run([*SWARMMAP, "world", "--floorplan", str(bad), "--export",
                           str(tmp_path / "x")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "plan.svg: not a valid SVG/XML" in proc.stderr
