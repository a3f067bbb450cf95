"""Procedural plans, their ground truth and mesh, planned paths, and LiDAR geometry."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from swarmmap.shared.world.floorplan import procedural
from swarmmap.shared.world.paths import check_paths, path_length, plan_paths, point_along
from swarmmap.shared.world.sensing import beam_samples, raycast_grid, sensor_model, validation_set


@pytest.fixture(scope="module")
def plan():
    return procedural(3, 2, seed=4)


def test_plan_is_seeded(plan):
    assert procedural(3, 2, seed=4).walls.equals(plan.walls)
    assert not procedural(3, 2, seed=5).walls.equals(plan.walls)


def test_rooms_free_walls_and_outside_occupied(plan):
    grid = plan.occupancy(0.05)
    centres = np.array([r.representative_point().coords[0] for r in plan.rooms])
    assert not grid.occupied(centres).any()
    wall_points = np.array([p.representative_point().coords[0] for p in plan.wall_parts()])
    assert grid.occupied(wall_points).all()
    x0, y0, x1, y1 = plan.bounds
    assert grid.occupied(np.array([[x0 - 0.3, y0 - 0.3], [x1 + 0.3, (y0 + y1) / 2]])).all()
    assert not grid.occupied(np.array([d.centroid.coords[0] for d in plan.doors])).any()
    assert "corridor" in plan.room_names


def test_mesh_is_watertight_and_exports_as_stl(plan, tmp_path):
    mesh = plan.mesh(2.5)
    assert mesh.is_watertight
    assert mesh.bounds[1][2] == pytest.approx(2.5) and mesh.bounds[0][2] == pytest.approx(0.0)
    assert mesh.volume == pytest.approx(plan.walls.area * 2.5, rel=1e-6)
    path = tmp_path / "plan.stl"
    path.write_bytes(mesh.export(file_type="stl"))
    back = trimesh.load(path)
    assert back.is_watertight and back.volume == pytest.approx(mesh.volume, rel=1e-6)


def test_paths_stay_in_free_space_and_cover_the_plan(plan):
    grid = plan.occupancy(0.05)
    fine = plan.occupancy(0.02)
    paths = plan_paths(plan, grid, robots=3, seed=4)
    visited = set()
    for path in paths:
        s = np.linspace(0, path_length(path), 3000)
        pts = np.array([point_along(path, v)[0] for v in s])
        assert not fine.occupied(pts).any(), "a path crosses a wall"
        for i, room in enumerate(plan.rooms):
            if any(room.contains(__import__("shapely").geometry.Point(p)) for p in pts[::10]):
                visited.add(i)
    assert visited == set(range(len(plan.rooms)))
    starts = {tuple(np.round(p[0], 2)) for p in paths}
    assert len(starts) == 3, "robots should start in different rooms"


def test_check_paths_names_bad_waypoints(plan):
    grid = plan.occupancy(0.05)
    x0, y0, x1, y1 = plan.bounds
    with pytest.raises(ValueError, match="waypoint 1 .* outside the map"):
        check_paths([np.array([[1.0, 1.0], [x1 + 5, 1.0]])], grid, "w.npy")
    wall = plan.wall_parts()[0].representative_point().coords[0]
    with pytest.raises(ValueError, match="inside a wall"):
        check_paths([np.array([[1.0, 1.0], wall])], grid, "w.npy")


def test_raycast_finds_a_wall_at_its_known_distance(plan):
    grid = plan.occupancy(0.02)
    room = plan.rooms[0]
    cx, cy = room.centroid.coords[0]
    ranges, hit = raycast_grid(grid, np.array([[cx, cy]]), np.array([[-np.pi / 2]]), max_range=20.0)
    assert hit[0, 0]
    assert ranges[0, 0] == pytest.approx(cy - room.bounds[1], abs=0.03)


def test_beam_samples_label_free_before_hit_and_occupied_at_hit():
    pts, labels = beam_samples(np.array([0.0, 0.0]), np.array([0.0, np.pi]), np.array([1.0, 3.5]),
                               np.array([True, False]), max_range=3.5, samples_per_beam=8, occupied_depth=0.05)
    occ = pts[labels == 1]
    assert occ.shape == (1, 2) and occ[0] == pytest.approx([1.05, 0.0], abs=1e-6)
    free = pts[labels == 0]
    assert (free[free[:, 1] == 0][:, 0] < 1.0).all()
    assert len(free[free[:, 0] < 0]) == 7  # the no-return beam: every sample but the shared origin
    pts2, labels2 = beam_samples(np.zeros(2), np.array([0.0]), np.array([2.0]), np.array([True]), 3.5, 50, 0.0,
                                 sampling="uniform", rng=np.random.default_rng(0))
    assert len(pts2) == 51 and (pts2[labels2 == 0][:, 0] < 2.0).all()


def test_sensor_model_noise_dropouts_and_max_range():
    rng = np.random.default_rng(0)
    ranges = np.full(20000, 2.0)
    hit = np.ones(20000, bool)
    r, h, valid = sensor_model(ranges, hit, rng, noise_std=0.05, dropout_prob=0.1, min_range=0.12, max_range=3.5)
    assert np.std(r) == pytest.approx(0.05, rel=0.05)
    assert (1 - valid.mean()) == pytest.approx(0.1, abs=0.01)
    r, h, _ = sensor_model(np.array([3.49, 1.0]), np.array([True, False]), np.random.default_rng(1), noise_std=0.5,
                           dropout_prob=0.0, min_range=0.12, max_range=3.5)
    assert not h[1] and r[1] == 3.5 and (r <= 3.5).all()


def test_validation_labels_agree_with_ground_truth(plan):
    grid = plan.occupancy(0.05)
    pts, labels = validation_set(grid, scans=20, beams=16, max_range=3.5, samples_per_beam=8, seed=0)
    assert len(pts) > 100 and 0 < labels.mean() < 0.5
    assert (grid.occupied(pts) == labels.astype(bool)).all()
