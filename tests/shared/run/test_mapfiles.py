"""A learned map's files: arrays, PNGs on the viewer's scales, and ROS map_server maps read back as plans."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
import yaml
from PIL import Image

from swarmmap.shared.run.config import WorldSettings
from swarmmap.shared.run.mapfiles import FREE_PIXEL, OCCUPIED_PIXEL, UNKNOWN_PIXEL, save_learned_map
from swarmmap.shared.world.plans import load_floorplan

RES, ORIGIN = 0.05, (-1.0, -0.5)


def learned(h: int = 60, w: int = 80, with_std: bool = True) -> dict[str, np.ndarray]:
    """A map (row 0 = south) of a free room inside a wall, an unsure band inside the wall,
    and an occupied block in the north-west corner to tell the orientation; its std grows
    from west to east."""
    mean = np.full((h, w), 0.9)
    mean[5:-5, 5:-5] = 0.4  # unsure: between the thresholds
    mean[8:-8, 8:-8] = 0.05
    mean[-20:-10, 10:20] = 0.95  # the marker, north-west
    maps = {"mean": mean, "origin": np.array(ORIGIN), "resolution": np.float64(RES)}
    if with_std:
        maps["std"] = np.tile(np.linspace(0, 0.3, w), (h, 1))
    return maps


def test_a_learned_map_is_written_as_arrays_pngs_and_ros_maps(tmp_path):
    maps = learned()
    written = save_learned_map(tmp_path, "robot-0", maps, std_max=0.25)
    assert {p.name for p in written} == {p.name for p in tmp_path.iterdir()} == {
        "robot-0.npz", "robot-0-mean.png", "robot-0.yaml", "robot-0.pgm",
        "robot-0-std.png", "robot-0-std.yaml", "robot-0-std.pgm"}
    with np.load(tmp_path / "robot-0.npz") as z:
        assert sorted(z.files) == ["mean", "origin", "resolution", "std"]
        np.testing.assert_array_equal(z["std"], maps["std"])
    mean_png = np.asarray(Image.open(tmp_path / "robot-0-mean.png"))
    assert mean_png.shape == (60, 80) and mean_png[0, 0] < 30 and mean_png[30, 40] > 230  # dark = occupied, north up
    assert mean_png[15, 15] < 30, "the north-west marker is in the image's top-left"


def test_the_std_png_is_magma_on_0_to_std_max_like_the_viewer(tmp_path):
    maps = learned()
    save_learned_map(tmp_path, "r", maps, std_max=0.25)
    png = np.asarray(Image.open(tmp_path / "r-std.png"))
    assert png.shape == (60, 80, 3)
    magma = matplotlib.colormaps["magma"]
    west, mid, east = png[30, 0], png[30, int(0.125 / 0.3 * 79)], png[30, -1]
    np.testing.assert_allclose(west, np.array(magma(0.0)[:3]) * 255, atol=2)  # std 0: magma's dark end
    np.testing.assert_allclose(east, np.array(magma(1.0)[:3]) * 255, atol=2)  # 0.3 > std_max: its bright end
    np.testing.assert_allclose(mid, np.array(magma(0.5)[:3]) * 255, atol=12)  # 0.125 = half of 0.25


def test_the_ros_map_is_trinary_and_loads_back_as_the_plan_it_shows(tmp_path):
    maps = learned()
    save_learned_map(tmp_path, "robot-0", maps, std_max=0.25)
    doc = yaml.safe_load((tmp_path / "robot-0.yaml").read_text())
    assert doc == {"image": "robot-0.pgm", "resolution": RES, "origin": [*ORIGIN, 0.0], "negate": 0,
                   "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary"}
    pixels = np.asarray(Image.open(tmp_path / "robot-0.pgm"))
    assert set(np.unique(pixels)) == {OCCUPIED_PIXEL, FREE_PIXEL, UNKNOWN_PIXEL}
    grid = load_floorplan(str(tmp_path / "robot-0.yaml"), WorldSettings(), 0).raster
    assert grid.resolution == pytest.approx(RES) and grid.origin == pytest.approx(ORIGIN)
    mean = maps["mean"]
    np.testing.assert_array_equal(grid.unknown, (mean >= 0.196) & (mean <= 0.65))
    np.testing.assert_array_equal(grid.grid == 0, mean < 0.196)
    x0, _, _, y1 = grid.bounds
    assert grid.occupied(np.array([[x0 + 15 * RES, y1 - 15 * RES]]))[0], "the marker is north-west"


def test_the_std_ros_map_states_its_scale(tmp_path):
    maps = learned()
    save_learned_map(tmp_path, "robot-0", maps, std_max=0.25)
    doc = yaml.safe_load((tmp_path / "robot-0-std.yaml").read_text())
    assert doc["image"] == "robot-0-std.pgm" and doc["mode"] == "scale"
    assert (doc["free_thresh"], doc["occupied_thresh"]) == (0.0, 1.0)  # occupancy linear in the std
    text = (tmp_path / "robot-0-std.yaml").read_text()
    assert text.startswith("# ") and "0.25 * (255 - pixel) / 255" in text
    raw = (tmp_path / "robot-0-std.pgm").read_bytes()
    assert raw.startswith(b"P5\n# ") and b"0.25 * (255 - pixel) / 255" in raw.split(b"\n255\n")[0]
    pixels = np.asarray(Image.open(tmp_path / "robot-0-std.pgm"))[::-1]  # row 0 = south again
    decoded = 0.25 * (255 - pixels.astype(float)) / 255
    np.testing.assert_allclose(decoded, np.minimum(maps["std"], 0.25), atol=0.25 / 255)


def test_a_deterministic_models_map_has_no_std_files(tmp_path):
    written = save_learned_map(tmp_path, "robot-3", learned(with_std=False), std_max=0.25)
    assert sorted(p.name for p in written) == ["robot-3-mean.png", "robot-3.npz", "robot-3.pgm", "robot-3.yaml"]
    with np.load(tmp_path / "robot-3.npz") as z:
        assert sorted(z.files) == ["mean", "origin", "resolution"]


def test_free_space_on_a_maps_edge_is_unknown_so_the_world_stays_closed(tmp_path):
    maps = learned()
    maps["mean"][:, :3] = 0.02  # the network guessed free space reaching the map's west edge
    save_learned_map(tmp_path, "edge", maps, std_max=0.25)
    grid = load_floorplan(str(tmp_path / "edge.yaml"), WorldSettings(), 0).raster
    assert grid.unknown[:, 0].all() and (grid.grid[:, 0] > 0).all(), "the edge is solid and no ground truth"
    assert (grid.grid[:, 1] == 0).any(), "free cells inside the edge stay free"


def test_map_pngs_carry_a_scale_bar_of_a_round_length(tmp_path):
    """A learned map's PNGs (0.05 m cells, 181 wide) show a 2 m bar (40 px) in the lower-left corner."""
    from PIL import Image

    from swarmmap.shared.run.mapfiles import save_learned_map

    maps = {"mean": np.full((191, 181), 0.5, np.float32), "std": np.full((191, 181), 0.1, np.float32),
            "resolution": np.float32(0.05), "origin": np.zeros(2, np.float32)}
    save_learned_map(tmp_path, "robot-0", maps, 0.25)
    for name in ("robot-0-mean.png", "robot-0-std.png"):
        px = np.asarray(Image.open(tmp_path / name).convert("L"))
        bar = px[-7:-4, 4:45]
        assert (bar == 0).all() and (px[-7:-4, 45:47] == 255).all(), name  # 40 px of black, then the white box
