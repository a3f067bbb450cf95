"""Floor plans from files: the CubiCasa5K sample, the DiNNO plan with its paths, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from PIL import Image

from swarmmap.shared.run.config import WorldSettings
from swarmmap.shared.world.floorplan import PlanError
from swarmmap.shared.world.paths import path_length, plan_paths, point_along
from swarmmap.shared.world.plans import load_floorplan
from tests.conftest import KIT_DATA

CUBICASA = KIT_DATA / "cubicasa5k" / "353" / "model.svg"
DINNO = KIT_DATA / "dinno-floorplan-32"
needs_cubicasa = pytest.mark.skipif(not CUBICASA.exists(), reason="kit data ../shared/data/cubicasa5k not present")
needs_dinno = pytest.mark.skipif(not DINNO.exists(), reason="kit data ../shared/data/dinno-floorplan-32 not present")


@needs_cubicasa
def test_cubicasa_sample_rooms_free_walls_occupied_and_extent():
    plan = load_floorplan(str(CUBICASA), WorldSettings(), seed=0)
    assert plan.kind == "cubicasa" and len(plan.rooms) == 17 and len(plan.doors) == 12
    x0, y0, x1, y1 = plan.bounds
    assert (x1 - x0, y1 - y0) == pytest.approx((10.007, 14.041), abs=0.02)
    grid = plan.occupancy(0.02)
    indoor = [r for r, name in zip(plan.rooms, plan.room_names) if name != "Outdoor"]
    assert not grid.occupied(np.array([r.representative_point().coords[0] for r in indoor])).any()
    assert grid.occupied(np.array([w.representative_point().coords[0] for w in plan.wall_parts()])).all()
    assert plan.mesh(2.5).is_watertight


@needs_cubicasa
def test_cubicasa_paths_cover_rooms_without_crossing_walls():
    plan = load_floorplan(str(CUBICASA), WorldSettings(), seed=0)
    grid = plan.occupancy(0.05)
    fine = plan.occupancy(0.02)
    paths = plan_paths(plan, grid, robots=3, seed=0)
    assert len(paths) == 3 and all(path_length(p) > 20 for p in paths)  # three robots, each driving through the house
    for path in paths:
        pts = np.array([point_along(path, s)[0] for s in np.linspace(0, path_length(path), 2000)])
        assert not fine.occupied(pts).any()
    # together they enter the rooms: every indoor room but at most one (the 1 m2 storage behind a narrow door)
    driven = shapely.MultiLineString([p for p in paths if len(p) > 1])
    indoor = [r for r, name in zip(plan.rooms, plan.room_names) if name != "Outdoor"]
    assert sum(driven.intersects(r) for r in indoor) >= len(indoor) - 1


@needs_dinno
def test_dinno_plan_and_its_seven_paths_lie_in_free_space():
    settings = WorldSettings(waypoints=str(DINNO / "tight_paths"))
    plan = load_floorplan(str(DINNO / "floor_img.png"), settings, seed=0)
    assert plan.kind == "dinno" and plan.image_size == (2167, 1608)
    assert len(plan.paths) == 7
    x0, y0, x1, y1 = plan.bounds
    assert (x1 - x0, y1 - y0) == pytest.approx((21.67, 16.08))
    lengths = [len(p) for p in plan.paths]
    assert lengths[0] == 30 * 81 and lengths[3] == 30 * 79  # DiNNO: 30 points per segment
    for path in plan.paths:
        assert not plan.raster.occupied(path).any()
    assert plan.mesh(2.5).is_watertight


@needs_dinno
def test_dinno_waypoints_keep_dinnos_orientation():
    """DiNNO's y grows with the image row: waypoint y = +1 maps to the image's bottom (south)."""
    plan = load_floorplan(str(DINNO / "floor_img.png"), WorldSettings(waypoints=str(DINNO / "tight_paths")), seed=0)
    raw = np.load(DINNO / "tight_paths" / "1.npy")
    first = plan.paths[0][0]
    assert first == pytest.approx([raw[0, 0] * 2167 / 2 / 100, -raw[0, 1] * 1608 / 2 / 100])


def write_png(path, array):
    Image.fromarray(array.astype(np.uint8)).save(path)
    return path


def test_missing_and_unknown_files_are_named(tmp_path):
    with pytest.raises(PlanError, match="nope.svg: file does not exist"):
        load_floorplan(str(tmp_path / "nope.svg"), WorldSettings(), 0)
    other = tmp_path / "plan.dxf"
    other.write_text("x")
    with pytest.raises(PlanError, match="plan.dxf: unknown floor-plan kind '.dxf'"):
        load_floorplan(str(other), WorldSettings(), 0)


def test_corrupt_and_foreign_svg_are_refused(tmp_path):
    bad = tmp_path / "model.svg"
    bad.write_text("<svg xmlns='http://www.w3.org/2000/svg'><g id='Wall'><polygon points='0,0 10,0")
    with pytest.raises(PlanError, match="model.svg: not a valid SVG/XML"):
        load_floorplan(str(bad), WorldSettings(), 0)
    foreign = tmp_path / "drawing.svg"
    foreign.write_text("<svg xmlns='http://www.w3.org/2000/svg'><rect width='10' height='10'/></svg>")
    with pytest.raises(PlanError, match="drawing.svg: no <g id=\"Wall\"> found"):
        load_floorplan(str(foreign), WorldSettings(), 0)


def test_png_without_free_space_and_corrupt_png(tmp_path):
    full = write_png(tmp_path / "full.png", np.full((100, 120), 255))
    with pytest.raises(PlanError, match="full.png: the image has no free space"):
        load_floorplan(str(full), WorldSettings(), 0)
    walled = write_png(tmp_path / "walled.png", np.zeros((50, 50)))  # free only inside a 30 px border
    with pytest.raises(PlanError, match="no free space"):
        load_floorplan(str(walled), WorldSettings(), 0)
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    with pytest.raises(PlanError, match="broken.png: not a readable PNG"):
        load_floorplan(str(broken), WorldSettings(), 0)


def test_an_image_too_large_to_open_is_refused_by_name_not_by_a_traceback(tmp_path):
    """A 20000 x 20000 one-bit PNG is 90 KB on disk and 400 M pixels: PIL refuses to open it at all
    (a decompression bomb, past twice its limit); a plan, and a ROS map's image, are named instead."""
    Image.new("1", (20000, 20000), 1).save(tmp_path / "bomb.png")
    assert (tmp_path / "bomb.png").stat().st_size < 200_000
    with pytest.raises(PlanError, match=r"bomb.png: image larger than 50000000 pixels \(400000000 pixels\)"):
        load_floorplan(str(tmp_path / "bomb.png"), WorldSettings(), 0)
    (tmp_path / "map.yaml").write_text("image: bomb.png\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
                                       "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    with pytest.raises(PlanError, match=r"bomb.png: image larger than 50000000 pixels"):
        load_floorplan(str(tmp_path / "map.yaml"), WorldSettings(), 0)


@pytest.fixture
def box_png(tmp_path):
    img = np.zeros((200, 300))
    img[90:110, 100:200] = 255  # a wall in the middle
    return write_png(tmp_path / "box.png", img)


def test_waypoints_outside_the_map_or_in_a_wall_are_named(tmp_path, box_png):
    folder = tmp_path / "paths"
    folder.mkdir()
    np.save(folder / "1.npy", np.array([[-0.5, -0.5], [-0.5, 0.5], [1.5, 0.0], [0.0, 0.5]]))
    with pytest.raises(PlanError, match=r"1.npy: DiNNO waypoints must lie in \[-1, 1\]"):
        load_floorplan(str(box_png), WorldSettings(waypoints=str(folder)), 0)
    np.save(folder / "1.npy", np.array([[-0.5, -0.5], [-0.5, 0.5], [0.0, 0.0], [0.5, -0.5]]))
    with pytest.raises(PlanError, match="1.npy: waypoint .* inside a wall"):
        load_floorplan(str(box_png), WorldSettings(waypoints=str(folder)), 0)


def test_truncated_or_foreign_waypoint_files_are_named(tmp_path, box_png):
    folder = tmp_path / "paths"
    folder.mkdir()
    np.save(folder / "1.npy", np.zeros((10, 2)))
    data = (folder / "1.npy").read_bytes()
    (folder / "1.npy").write_bytes(data[: len(data) - 30])
    with pytest.raises(PlanError, match="1.npy: not a readable .npy"):
        load_floorplan(str(box_png), WorldSettings(waypoints=str(folder)), 0)
    np.save(folder / "1.npy", np.zeros((10, 3)))
    with pytest.raises(PlanError, match=r"1.npy: waypoints must be a numeric \(K, 2\) array"):
        load_floorplan(str(box_png), WorldSettings(waypoints=str(folder)), 0)
    (folder / "1.npy").write_text("hello")
    with pytest.raises(PlanError, match="1.npy: not a readable .npy"):
        load_floorplan(str(box_png), WorldSettings(waypoints=str(folder)), 0)


def test_a_missing_sample_file_says_where_the_sample_data_comes_from(tmp_path):
    """A plan or log under ``shared/data`` that is not there: the refusal points at the README's Sample data."""
    from swarmmap.shared.world.datasets import DatasetError, read_log

    with pytest.raises(PlanError, match="sample data, kept beside the repository.*README's 'Sample data'"):
        load_floorplan(str(tmp_path / "shared" / "data" / "cubicasa5k" / "353" / "model.svg"), WorldSettings(), 0)
    with pytest.raises(DatasetError, match="no such file or folder \\(sample data"):
        read_log(tmp_path / "shared" / "data" / "carmen" / "intel-corrected.log.gz")
