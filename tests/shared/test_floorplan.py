"""Procedural plans, their ground truth, robot paths and LiDAR geometry."""

from __future__ import annotations

import numpy as np
import pytest

from swarmmap.shared.floorplan import plan_paths, point_along, procedural
from swarmmap.shared.sensing import beam_samples, raycast_grid, validation_set


@pytest.fixture(scope="module")
def plan():
    return procedural(3, 2, seed=4)


def test_plan_is_seeded(plan):
    assert procedural(3, 2, seed=4).walls == plan.walls
    assert procedural(3, 2, seed=5).walls != plan.walls


def test_rooms_free_walls_and_outside_occupied(plan):
    grid = plan.occupancy(0.05)
    centres = np.array([r.centre for r in plan.rooms])
    assert not grid.occupied(centres).any()
    wall_centres = np.array([((w.x0 + w.x1) / 2, (w.y0 + w.y1) / 2) for w in plan.walls])
    assert grid.occupied(wall_centres).all()
    x0, y0, x1, y1 = plan.bounds
    assert grid.occupied(np.array([[x0 - 0.3, y0 - 0.3], [x1 + 0.3, (y0 + y1) / 2]])).all()
    assert not grid.occupied(np.array([d.centre for d in plan.doors])).any()


def test_every_room_reachable_through_doors(plan):
    seen, todo = {0}, [0]
    while todo:
        here = todo.pop()
        for d in plan.doors:
            for a, b in ((d.a, d.b), (d.b, d.a)):
                if a == here and b not in seen:
                    seen.add(b)
                    todo.append(b)
    assert seen == set(range(len(plan.rooms)))


def test_paths_stay_in_free_space_and_cover_the_plan(plan):
    grid = plan.occupancy(0.02)
    paths = plan_paths(plan, robots=3, seed=4)
    visited = set()
    for path in paths:
        length = np.linalg.norm(np.diff(path, axis=0), axis=1).sum()
        s = np.linspace(0, length, 2000)
        pts = np.array([point_along(path, v)[0] for v in s])
        assert not grid.occupied(pts).any(), "a path crosses a wall"
        for i, room in enumerate(plan.rooms):
            if ((pts[:, 0] > room.x0) & (pts[:, 0] < room.x1) & (pts[:, 1] > room.y0) & (pts[:, 1] < room.y1)).any():
                visited.add(i)
    assert visited == set(range(len(plan.rooms)))


def test_raycast_finds_a_wall_at_its_known_distance(plan):
    grid = plan.occupancy(0.02)
    room = plan.rooms[0]
    cx, cy = room.centre
    # Beam towards +y from the room centre hits the room's northern wall face at room.y1.
    ranges, hit = raycast_grid(grid, np.array([[cx, cy]]), np.array([[np.pi / 2]]), max_range=20.0)
    assert hit[0, 0]
    assert ranges[0, 0] == pytest.approx(room.y1 - cy, abs=0.03)


def test_beam_samples_label_free_before_hit_and_occupied_at_hit():
    pts, labels = beam_samples(np.array([0.0, 0.0]), np.array([0.0, np.pi]), np.array([1.0, 3.5]),
                               np.array([True, False]), max_range=3.5, samples_per_beam=8, occupied_depth=0.05)
    occ = pts[labels == 1]
    assert occ.shape == (1, 2) and occ[0] == pytest.approx([1.05, 0.0], abs=1e-6)
    free = pts[labels == 0]
    beam0 = free[free[:, 0] >= 0]
    assert (beam0[:, 0] < 1.0).all() and len(beam0) == 3  # 0, 0.5, 1.0- spacing of 3.5/7 -> 0, .5
    assert len(free[free[:, 0] < 0]) == 7  # the no-return beam keeps every sample but the shared origin


def test_validation_labels_agree_with_ground_truth(plan):
    grid = plan.occupancy(0.05)
    pts, labels = validation_set(grid, scans=20, beams=16, max_range=3.5, samples_per_beam=8, seed=0)
    assert len(pts) > 100 and 0 < labels.mean() < 0.5
    assert (grid.occupied(pts) == labels.astype(bool)).all()
