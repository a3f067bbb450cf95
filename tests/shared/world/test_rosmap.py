"""ROS map_server maps (.yaml + image) and paths on plans without room outlines or waypoints."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from PIL import Image

from swarmmap.services.world.simulation import robot_paths, wire_grid
from swarmmap.shared.run.config import RunConfig, WorldSettings
from swarmmap.shared.world.floorplan import PlanError
from swarmmap.shared.world.paths import coverage, path_length, plan_paths, point_along
from swarmmap.shared.world.plans import load_floorplan
from swarmmap.shared.world.sensing import validation_set
from tests.conftest import KIT_DATA

FREE, WALL, UNKNOWN = 254, 0, 205  # what map_saver writes (trinary)
DINNO = KIT_DATA / "dinno-floorplan-32"


def two_rooms(h: int = 200, w: int = 300) -> np.ndarray:
    """An image (row 0 = top): unknown all round, a walled building of two rooms joined by a
    door, and a wall block in the building's top-left corner to tell the orientation."""
    img = np.full((h, w), UNKNOWN, np.uint8)
    img[20:-20, 20:-20] = WALL
    img[24:-24, 24:-24] = FREE
    img[24:-24, w // 2 - 2 : w // 2 + 2] = WALL  # the middle wall ...
    img[h // 2 - 12 : h // 2 + 12, w // 2 - 2 : w // 2 + 2] = FREE  # ... with a door
    img[24:44, 24:54] = WALL  # the marker: top-left
    return img


def write_map(folder, img, name="map", mode=None, **fields):
    fmt = "PNG" if img.ndim == 3 else "PPM"
    image = folder / (f"{name}.png" if img.ndim == 3 else f"{name}.pgm")
    Image.fromarray(img).save(image, format=fmt)
    doc = {"image": image.name, "resolution": 0.05, "origin": [-2.0, -1.0, 0.0], "negate": 0,
           "occupied_thresh": 0.65, "free_thresh": 0.196}
    if mode:
        doc["mode"] = mode
    doc.update(fields)
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_a_ros_map_is_read_as_map_server_reads_it(tmp_path):
    img = two_rooms()
    plan = load_floorplan(str(write_map(tmp_path, img)), WorldSettings(), 0)
    assert plan.kind == "rosmap"
    grid = plan.raster
    assert grid.bounds == pytest.approx((-2.0, -1.0, -2.0 + 300 * 0.05, -1.0 + 200 * 0.05))
    # origin is the lower-left pixel: the image's bottom row is the grid's row 0
    np.testing.assert_array_equal(grid.grid, (img != FREE)[::-1].astype(np.uint8))
    np.testing.assert_array_equal(grid.unknown, (img == UNKNOWN)[::-1])
    # the marker, in the image's top-left, lies at small x and large y
    x0, _, _, y1 = grid.bounds
    assert grid.occupied(np.array([[x0 + 40 * 0.05, y1 - 34 * 0.05]]))[0]
    assert not grid.unknown[grid.cells(np.array([[x0 + 40 * 0.05, y1 - 34 * 0.05]]))[:2]][0]


def test_negate_modes_thresholds_and_transparency(tmp_path):
    img = two_rooms()
    base = load_floorplan(str(write_map(tmp_path, img)), WorldSettings(), 0).raster
    negated = load_floorplan(str(write_map(tmp_path, 255 - img, "neg", negate=1)), WorldSettings(), 0).raster
    np.testing.assert_array_equal(negated.grid, base.grid)
    np.testing.assert_array_equal(negated.unknown, base.unknown)
    scale = load_floorplan(str(write_map(tmp_path, img, "scale", mode="scale")), WorldSettings(), 0).raster
    np.testing.assert_array_equal(scale.unknown, base.unknown)  # in-between values: no ground truth
    raw_img = np.where(img == FREE, 0, np.where(img == WALL, 100, 255)).astype(np.uint8)
    raw = load_floorplan(str(write_map(tmp_path, raw_img, "raw", mode="raw")), WorldSettings(), 0).raster
    np.testing.assert_array_equal(raw.grid, base.grid)
    np.testing.assert_array_equal(raw.unknown, base.unknown)
    # a lower occupied_thresh turns the grey (occupancy 0.2) into walls, not unknown
    low = load_floorplan(str(write_map(tmp_path, img, "low", occupied_thresh=0.19, free_thresh=0.1)),
                         WorldSettings(), 0).raster
    assert not low.unknown.any() and low.grid.sum() == base.grid.sum()
    rgba = np.dstack([img, img, img, np.where(img == UNKNOWN, 0, 255).astype(np.uint8)])
    rgba[..., :3][img == UNKNOWN] = FREE  # transparent pixels are unknown whatever their colour
    alpha = load_floorplan(str(write_map(tmp_path, rgba, "alpha")), WorldSettings(), 0).raster
    np.testing.assert_array_equal(alpha.unknown, base.unknown)


@pytest.mark.parametrize("fields, problem", [
    ({"mode": "fancy"}, "unknown mode 'fancy'"),
    ({"free_thresh": 0.7}, "free_thresh 0.7 must be below occupied_thresh"),
    ({"origin": [0.0, 0.0, 0.5]}, "a rotated map"),
    ({"origin": "here"}, "origin must be"),
    ({"resolution": -1}, "resolution must be"),
    ({"negate": 2}, "negate must be 0 or 1"),
    ({"image": "nowhere.pgm"}, "nowhere.pgm: not a readable map image"),
])
def test_bad_ros_maps_are_refused_naming_the_problem(tmp_path, fields, problem):
    path = write_map(tmp_path, two_rooms(), **fields)
    with pytest.raises(PlanError, match=problem):
        load_floorplan(str(path), WorldSettings(), 0)


def test_a_ros_map_without_free_space_or_keys_is_refused(tmp_path):
    with pytest.raises(PlanError, match="no free cell"):
        load_floorplan(str(write_map(tmp_path, np.full((50, 50), UNKNOWN, np.uint8))), WorldSettings(), 0)
    bare = tmp_path / "bare.yaml"
    bare.write_text("image: x.pgm\n")
    with pytest.raises(PlanError, match="bare.yaml: ROS map YAML lacks resolution, origin"):
        load_floorplan(str(bare), WorldSettings(), 0)
    bare.write_text("[1, 2")
    with pytest.raises(PlanError, match="not a readable ROS map YAML"):
        load_floorplan(str(bare), WorldSettings(), 0)


def test_robots_drive_through_a_ros_map_without_waypoints_and_unknown_is_no_ground_truth(tmp_path):
    plan = load_floorplan(str(write_map(tmp_path, two_rooms())), WorldSettings(), 0)
    grid = plan.occupancy(0.05)
    paths = plan_paths(plan, grid, robots=3, seed=0)
    assert all(path_length(p) > 5.0 for p in paths), [path_length(p) for p in paths]
    assert coverage(paths, grid, 3.5) > 0.95
    for path in paths:
        pts = np.array([point_along(path, s)[0] for s in np.linspace(0, path_length(path), 500)])
        assert not grid.occupied(pts).any()
    assert {bool(p[:, 0].mean() < 5.5) for p in paths} == {True, False}, "both rooms are driven through"
    pts, labels = validation_set(grid, 100, 60, 3.5, 10, seed=0)
    r, c, _ = grid.cells(pts)
    assert len(pts) > 1000 and not grid.unknown[r, c].any()
    assert set(np.unique(labels)) == {0.0, 1.0}
    wire = wire_grid(grid)
    assert set(np.unique(wire)) == {0, 1, 2} and (wire == 2).sum() == grid.unknown.sum()


def test_no_drivable_space_is_a_clear_error_not_a_robot_standing_still(tmp_path):
    img = np.full((100, 100), WALL, np.uint8)
    img[40:46, 40:46] = FREE  # 30 cm of free space: no robot fits with 20 cm clearance
    cfg = RunConfig()
    plan = load_floorplan(str(write_map(tmp_path, img)), cfg.world, 0)
    with pytest.raises(PlanError, match="no free space a robot can"):
        robot_paths(cfg, plan, plan.occupancy(0.05))


@pytest.mark.skipif(not DINNO.exists(), reason="kit data ../shared/data/dinno-floorplan-32 not present")
def test_the_dinno_image_without_its_waypoints_gets_paths_through_all_of_it():
    cfg = RunConfig()
    plan = load_floorplan(str(DINNO / "floor_img.png"), cfg.world, 0)
    grid = plan.occupancy(cfg.world.grid_resolution_m)
    paths = robot_paths(cfg.model_copy(update={"robots": 7}), plan, grid)
    assert len(paths) == 7 and all(path_length(p) > 5.0 for p in paths), [path_length(p) for p in paths]
    assert coverage(paths, grid, cfg.world.lidar_max_range_m) > 0.95
