"""A ground-truth occupancy grid (:class:`OccupancyGrid`): what a learner, the world and the tools
share of a floor plan. Apart from :mod:`~swarmmap.shared.world.floorplan` so that a process that
only reads grids (a learner) does not load the plans' geometry (shapely)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class OccupancyGrid:
    """``grid[r, c]`` (1 = occupied) covers x in [ox + c*res, +res), y in [oy + r*res, +res)."""

    grid: np.ndarray
    resolution: float
    origin: tuple[float, float]
    unknown: np.ndarray | None = None  # cells nobody knows (a ROS map's): solid in the world, never ground truth

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        h, w = self.grid.shape
        return self.origin[0], self.origin[1], self.origin[0] + w * self.resolution, self.origin[1] + h * self.resolution

    def resample(self, resolution: float) -> OccupancyGrid:
        """The same ground truth at another cell size (nearest cell)."""
        if math.isclose(resolution, self.resolution):
            return self
        x0, y0, x1, y1 = self.bounds
        out = OccupancyGrid(np.ones((int(math.ceil((y1 - y0) / resolution)), int(math.ceil((x1 - x0) / resolution))),
                                    dtype=np.uint8), resolution, self.origin)
        pts, shape = out.centres()
        out.grid[:] = self.occupied(pts).reshape(shape)
        if self.unknown is not None:
            rows, cols, inside = self.cells(pts)
            out.unknown = (self.unknown[rows, cols] & inside).reshape(shape)
        return out

    def clearance(self) -> np.ndarray:
        """Distance (m) from each cell centre to the nearest occupied cell (0 on occupied cells)."""
        from scipy import ndimage

        return ndimage.distance_transform_edt(self.grid == 0) * self.resolution

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, inside) of points ``xy`` (..., 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        cols = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        rows = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        h, w = self.grid.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        return np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1), inside

    def occupied(self, xy: np.ndarray) -> np.ndarray:
        """Occupancy (bool) at points ``xy`` (..., 2); outside the grid counts as occupied."""
        rows, cols, inside = self.cells(xy)
        return (self.grid[rows, cols] > 0) | ~inside

    def centres(self, resolution: float | None = None) -> tuple[np.ndarray, tuple[int, int]]:
        """Points (H*W, 2) on a grid over the bounds at ``resolution`` (row-major, y up), and (H, W)."""
        res = resolution or self.resolution
        x0, y0, x1, y1 = self.bounds
        xs = np.arange(x0 + res / 2, x1, res)
        ys = np.arange(y0 + res / 2, y1, res)
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx.ravel(), gy.ravel()], axis=1), (len(ys), len(xs))

    def random_free(self, n: int, rng: np.random.Generator, clearance: float = 0.0) -> np.ndarray:
        """``n`` points drawn uniformly from free cells at least ``clearance`` from anything occupied."""
        free = self.clearance() > clearance if clearance > 0 else self.grid == 0
        rows, cols = np.nonzero(free)
        if len(rows) == 0:
            raise ValueError("the occupancy grid has no free cell" + (f" {clearance} m from a wall" if clearance else ""))
        pick = rng.integers(0, len(rows), size=n)
        jitter = rng.uniform(0, 1, size=(n, 2))
        x = self.origin[0] + (cols[pick] + jitter[:, 0]) * self.resolution
        y = self.origin[1] + (rows[pick] + jitter[:, 1]) * self.resolution
        return np.stack([x, y], axis=1)
