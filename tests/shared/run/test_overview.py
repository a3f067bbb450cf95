"""A run's overview.png: ground truth beside each robot's mean, std and error maps on the viewer's scales."""

from __future__ import annotations

import io

import matplotlib
import numpy as np
import pytest
from PIL import Image

from swarmmap.shared.run.overview import error_map, truth_on, write_overview
from swarmmap.shared.world.grid import OccupancyGrid

RES, ORIGIN = 0.05, (-0.5, -0.5)


def truth(h: int = 40, w: int = 60) -> np.ndarray:
    """0 free, 1 occupied, 2 unknown (as groundtruth.npz holds it): a walled room, unknown all round."""
    grid = np.full((h, w), 2, np.uint8)
    grid[2:-2, 2:-2] = 1
    grid[4:-4, 4:-4] = 0
    return grid


def run_dir_with(tmp_path, robots: dict[int, bool]):
    """A run directory with a ground truth and, per robot, maps (with a std where ``robots`` says)
    and training points."""
    grid = truth()
    tmp_path.mkdir(parents=True, exist_ok=True)
    np.savez(tmp_path / "groundtruth.npz", grid=grid, resolution=RES, origin=np.array(ORIGIN),
             val_points=np.zeros((0, 2)), val_labels=np.zeros(0))
    (tmp_path / "maps").mkdir()
    (tmp_path / "data").mkdir()
    rng = np.random.default_rng(0)
    for robot, with_std in robots.items():
        mean = np.clip((grid == 1) + rng.normal(0, 0.05, grid.shape), 0, 1)
        maps = {"mean": mean, "origin": np.array(ORIGIN), "resolution": RES}
        if with_std:
            maps["std"] = np.where(grid == 2, 0.24, 0.01)
        np.savez(tmp_path / "maps" / f"robot-{robot}.npz", **maps)
        np.savez(tmp_path / "data" / f"robot-{robot}.npz", points=rng.uniform(0, 2, (500, 2)), labels=rng.integers(0, 2, 500))
    return tmp_path


def colour_share(img: np.ndarray, cmap: str, lo: float, hi: float) -> float:
    """Share of ``img``'s pixels within a few levels of ``cmap`` between ``lo`` and ``hi``."""
    lut = (matplotlib.colormaps[cmap](np.linspace(lo, hi, 32))[:, :3] * 255)
    packed, counts = np.unique(img[..., :3].astype(np.int64) @ np.array([1 << 16, 1 << 8, 1]), return_counts=True)
    colours = np.stack([packed >> 16, (packed >> 8) & 255, packed & 255], axis=1)
    near = (np.abs(colours[:, None, :].astype(float) - lut[None]).max(axis=2) < 4).any(axis=1)
    return float(counts[near].sum() / counts.sum())


def test_one_row_per_robot_and_a_std_column_only_for_models_with_one(tmp_path):
    bnn = np.asarray(Image.open(write_overview(run_dir_with(tmp_path / "a", {0: True, 1: True, 2: True}))))
    fourier_dir = run_dir_with(tmp_path / "b", {0: False, 1: False, 2: False})
    fourier = np.asarray(Image.open(write_overview(fourier_dir)))
    single = np.asarray(Image.open(write_overview(run_dir_with(tmp_path / "c", {0: True}))))
    assert bnn.shape[0] > 2 * single.shape[0], "a row per robot: three against one"
    assert bnn.shape[1] > fourier.shape[1] * 1.2, "the std column"
    # bright magma (std near std_max) only where a std map is drawn
    assert colour_share(bnn, "magma", 0.8, 1.0) > 0.01
    assert colour_share(fourier, "magma", 0.8, 1.0) < 0.001


def test_the_error_map_and_its_caption_cover_the_known_cells_only():
    grid = OccupancyGrid(np.array([[0, 1], [1, 0]], np.uint8), RES, ORIGIN, unknown=np.array([[False, False], [False, True]]))
    maps = {"mean": np.array([[0.2, 0.4], [0.9, 0.9]]), "origin": np.array(ORIGIN), "resolution": RES}
    occupied, known = truth_on(grid, maps)
    err, caption = error_map(maps, occupied, known)
    np.testing.assert_allclose(err[known], [0.2, 0.6, 0.1])
    assert np.isnan(err[1, 1])
    assert caption == "|mean - truth| 0.300, 66.7% right"


def test_the_truth_is_resampled_to_a_coarser_map():
    grid = OccupancyGrid(np.kron(np.array([[0, 1], [1, 1]], np.uint8), np.ones((4, 4), np.uint8)), RES, ORIGIN)
    occupied, known = truth_on(grid, {"mean": np.zeros((2, 2)), "origin": np.array(ORIGIN), "resolution": 4 * RES})
    np.testing.assert_array_equal(occupied, [[False, True], [True, True]])
    assert known.all()


def test_no_overview_without_ground_truth_or_maps(tmp_path, caplog):
    assert write_overview(tmp_path) is None and "groundtruth.npz is missing" in caplog.text
    run_dir_with(tmp_path, {})
    assert write_overview(tmp_path) is None and "holds no robot-<i>.npz" in caplog.text
    assert not (tmp_path / "overview.png").exists()


def test_a_rewritten_overview_is_whole(tmp_path):
    run_dir = run_dir_with(tmp_path, {0: True, 1: False})
    first = write_overview(run_dir, notes={0: "val_bce 0.0500"})
    Image.open(io.BytesIO(first.read_bytes())).verify()
    assert [p.name for p in run_dir.iterdir() if p.name.startswith(".")] == [], "no temporary file left behind"
    before = first.read_bytes()
    np.savez(run_dir / "maps" / "robot-1.npz", std=np.zeros((40, 60)))  # maps without a mean: refused
    with pytest.raises(KeyError):
        write_overview(run_dir)
    assert first.read_bytes() == before, "the figure already written stays"
