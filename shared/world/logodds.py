"""The classic log-odds occupancy grid: the map a robotics user knows, as a reference for learned maps.

Every beam lowers the log-odds of the cells it crosses (``log(p_miss / (1 - p_miss))``) and
raises the cell it ends in when it hits (``log(p_hit / (1 - p_hit))``), each cell counted once
per beam (twice at most where the march crosses from one slab of steps to the next); the sum is
clamped to [``logit(p_min)``, ``logit(p_max)``] once, where OctoMap clamps after every update.
The bounds and probabilities are OctoMap's (hit 0.7, miss 0.4, clamping 0.1192 and 0.971). A
cell no beam reached stays at 0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def logit(p: float) -> float:
    return math.log(p / (1 - p))


@dataclass(frozen=True)
class InverseSensorModel:
    p_hit: float = 0.7
    p_miss: float = 0.4
    p_min: float = 0.1192
    p_max: float = 0.971


@dataclass
class LogOddsGrid:
    """``logodds[r, c]`` covers x in [ox + c*res, +res), y in [oy + r*res, +res) (row 0 south)."""

    logodds: np.ndarray
    resolution: float
    origin: tuple[float, float]
    hits: np.ndarray | None = None  # beams that ended in each cell
    misses: np.ndarray | None = None  # beams that crossed it

    def probability(self) -> np.ndarray:
        """Occupancy probability (H, W) float32."""
        return (1.0 / (1.0 + np.exp(-self.logodds))).astype(np.float32)

    def cell_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat cell index of each of ``points`` (M, 2) and whether it lies in the grid."""
        h, w = self.logodds.shape
        cols = np.floor((points[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        rows = np.floor((points[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        return np.clip(rows, 0, h - 1) * w + np.clip(cols, 0, w - 1), inside

    def at(self, points: np.ndarray) -> np.ndarray:
        """Occupancy probability at ``points`` (M, 2); 0.5 outside the grid."""
        index, inside = self.cell_index(np.asarray(points, np.float64))
        p = self.probability().ravel()[index]
        return np.where(inside, p, np.float32(0.5))

    def plus(self, other: LogOddsGrid, model: InverseSensorModel | None = None) -> LogOddsGrid:
        """The grid of this one's beams and ``other``'s (the same cells; both built with counts)."""
        hits, misses = self.hits + other.hits, self.misses + other.misses
        return LogOddsGrid(log_odds(hits, misses, model or InverseSensorModel()), self.resolution, self.origin, hits, misses)

    def known(self) -> np.ndarray:
        """Cells some beam reached (H, W) bool."""
        return self.logodds != 0 if self.hits is None else (self.hits + self.misses) > 0


def build_logodds(shape: tuple[int, int], origin: tuple[float, float], resolution: float, positions: np.ndarray,
                  angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray, model: InverseSensorModel | None = None,
                  chunk_beams: int = 20000) -> LogOddsGrid:
    """The grid over ``shape`` cells from beams: ``positions`` (N, 2) of their scans, absolute
    ``angles`` (N, B), ``ranges`` (N, B) (a no-hit beam's range is how far it saw free space) and
    ``hit`` (N, B)."""
    model = model or InverseSensorModel()
    h, w = shape
    grid = LogOddsGrid(np.zeros(shape, np.float32), resolution, (float(origin[0]), float(origin[1])))
    n_cells = h * w
    misses = np.zeros(n_cells, np.int64)
    hits = np.zeros(n_cells, np.int64)
    pos = np.repeat(np.asarray(positions, np.float64), np.shape(angles)[1], axis=0)
    a, r, k = np.asarray(angles, np.float64).ravel(), np.asarray(ranges, np.float64).ravel(), np.asarray(hit, bool).ravel()
    step = resolution / 2
    for s in range(0, len(a), chunk_beams):
        sl = slice(s, s + chunk_beams)
        pa, ra, ka, aa = pos[sl], r[sl], k[sl], a[sl]
        end = pa + ra[:, None] * np.stack([np.cos(aa), np.sin(aa)], 1)
        end_cell, end_in = grid.cell_index(end)
        t = np.arange(0.0, float(ra.max(initial=0.0)) + step, step)
        for lo in range(0, len(t), 256):  # march in slabs of steps to bound memory
            tt = t[lo : lo + 256]
            along = tt[None, :] < ra[:, None]  # (b, T)
            if not along.any():
                break
            beam, j = np.nonzero(along)
            pts = pa[beam] + tt[j, None] * np.stack([np.cos(aa[beam]), np.sin(aa[beam])], 1)
            cell, inside = grid.cell_index(pts)
            keep = inside & ~(ka[beam] & (cell == end_cell[beam]))  # a hit's own cell is not free
            # Each cell a beam crosses once: a straight beam's samples of one cell are consecutive (rows
            # and columns change monotonically along it), so a change of (beam, cell) starts a new one.
            beam, cell = beam[keep], cell[keep]
            new = np.ones(len(cell), bool)
            new[1:] = (cell[1:] != cell[:-1]) | (beam[1:] != beam[:-1])
            misses += np.bincount(cell[new], minlength=n_cells)
        # A beam crossing a cell in two slabs counts twice there at most: slabs are 128 cells long.
        hits += np.bincount(end_cell[ka & end_in], minlength=n_cells)
    grid.hits, grid.misses = hits.reshape(shape), misses.reshape(shape)
    grid.logodds = log_odds(grid.hits, grid.misses, model)
    return grid


def log_odds(hits: np.ndarray, misses: np.ndarray, model: InverseSensorModel) -> np.ndarray:
    """Each cell's log-odds from the beams that ended in it and crossed it, clamped (float32)."""
    l_hit, l_miss = logit(model.p_hit), logit(model.p_miss)
    return np.clip(hits * l_hit + misses * l_miss, logit(model.p_min), logit(model.p_max)).astype(np.float32)


def bce(p: np.ndarray, labels: np.ndarray, eps: float = 1e-6) -> float:
    """Mean binary cross-entropy of predicted occupancies ``p`` against 0/1 ``labels``."""
    p = np.clip(np.asarray(p, np.float64), eps, 1 - eps)
    y = np.asarray(labels, np.float64)
    return float(-(y * np.log(p) + (1 - y) * np.log(1 - p)).mean())
