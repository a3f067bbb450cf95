"""Where a robot has no data: the places its Bayesian network is taught to be unsure of.

:class:`Coverage` lays a grid of ``margin / 2`` cells over the map's bounds and marks the cells
within ``margin`` of any of the robot's training points (its own coverage). Cells no robot is
known to have covered are where the noise-contrastive prior
(:func:`swarmmap.shared.learning.bnn.function_prior_kl`) samples its points. Teammates' coverage, as
their States carry it (a packed bit per cell, ``learner.share_coverage``), is merged in, so a
robot does not teach its network to doubt a room that a teammate has mapped and whose
parameters consensus brings it.
"""

from __future__ import annotations

import math

import numpy as np
import torch

MAX_PENDING_ROUNDS = 16  # rounds of offered coverage held at once (Algorithm 1 needs two or three)


class Coverage:
    """The covered cells of a grid over ``bounds`` (x0, y0, x1, y1), with cells of ``margin / 2``."""

    def __init__(self, bounds: tuple[float, float, float, float], margin: float, points: np.ndarray):
        if margin <= 0:
            raise ValueError(f"the margin around the data must be positive, not {margin}")
        x0, y0, x1, y1 = (float(b) for b in bounds)
        self.origin = np.array([x0, y0])
        self.cell = margin / 2
        self.shape = (max(1, math.ceil((y1 - y0) / self.cell)), max(1, math.ceil((x1 - x0) / self.cell)))
        self.margin = margin
        self.own = self._covered(points)
        self.others = np.zeros(self.shape, bool)
        self._free: torch.Tensor | None = None
        self.pending: dict[int, np.ndarray] = {}  # round -> cells offered with States of it, merged by advance()

    @property
    def cells(self) -> int:
        return self.shape[0] * self.shape[1]

    def _covered(self, points: np.ndarray) -> np.ndarray:
        seen = np.zeros(self.shape, bool)
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        if len(pts):
            cols = np.floor((pts[:, 0] - self.origin[0]) / self.cell).astype(np.int64)
            rows = np.floor((pts[:, 1] - self.origin[1]) / self.cell).astype(np.int64)
            inside = (rows >= 0) & (rows < self.shape[0]) & (cols >= 0) & (cols < self.shape[1])
            seen[rows[inside], cols[inside]] = True
        if not seen.any():
            return seen
        # a cell is covered when its centre lies within the margin of a cell holding data
        from scipy.ndimage import distance_transform_edt  # (only where a prior is on: not in every learner)

        return distance_transform_edt(~seen) * self.cell <= self.margin

    def covered(self) -> np.ndarray:
        """Cells this robot or a teammate it heard of covers."""
        return self.own | self.others

    def packed(self) -> np.ndarray:
        """:meth:`covered` as bits (numpy's packbits order, row-major), as a State carries it."""
        return np.packbits(self.covered().reshape(-1))

    def unpack(self, packed: np.ndarray) -> np.ndarray:
        """Cells from bits as :meth:`packed` makes them; ValueError for a bit string of the wrong length."""
        bits = np.asarray(packed, np.uint8).reshape(-1)
        if len(bits) != (self.cells + 7) // 8:
            raise ValueError(f"coverage of {len(bits)} bytes for a grid of {self.cells} cells "
                             f"(expected {(self.cells + 7) // 8})")
        return np.unpackbits(bits, count=self.cells).astype(bool).reshape(self.shape)

    def offer(self, round: int, packed: np.ndarray) -> None:
        """A teammate's coverage that came with its State of training round ``round``, merged by
        :meth:`advance` once this node is past that round: when a State arrives does not change
        the run (a run over Zenoh equals the one in process). ValueError as :meth:`unpack`."""
        cells = self.unpack(packed)
        if round not in self.pending and len(self.pending) >= MAX_PENDING_ROUNDS:
            # a flood of rounds: memory stays bounded by folding the farthest-ahead round into
            # this one (or this one into it), so a round far ahead holds nothing back
            top = max(self.pending)
            if round < top:
                cells = cells | self.pending.pop(top)
            else:
                round = top
        if round in self.pending:
            self.pending[round] |= cells
        else:
            self.pending[round] = cells

    def advance(self, k: int) -> bool:
        """Merge the coverage offered with States of rounds before ``k``; whether any cell was new."""
        ready = [r for r in self.pending if r < k]
        if not ready:
            return False
        return self.merge_cells(np.logical_or.reduce([self.pending.pop(r) for r in ready]))

    def merge_cells(self, theirs: np.ndarray) -> bool:
        """Add cells (a bool array of the grid's shape) that teammates cover; whether any was new."""
        new = theirs & ~self.covered()
        if not new.any():
            return False
        self.others |= theirs
        self._free = None
        return True

    def set_points(self, points: np.ndarray) -> None:
        """Replace this robot's own data (online training's sliding window keeps what it covered)."""
        self.own |= self._covered(points)
        self._free = None

    def uncovered_fraction(self) -> float:
        return float(1.0 - self.covered().mean())

    def sample(self, n: int, generator: torch.Generator, device: torch.device | str = "cpu") -> torch.Tensor | None:
        """``n`` points drawn uniformly over the uncovered cells (None when every cell is covered)."""
        if self._free is None:
            self._free = torch.from_numpy(np.flatnonzero(~self.covered().reshape(-1)))
        if len(self._free) == 0 or n <= 0:
            return None
        pick = self._free[torch.randint(0, len(self._free), (n,), generator=generator)]
        rows, cols = pick // self.shape[1], pick % self.shape[1]
        jitter = torch.rand((n, 2), generator=generator, dtype=torch.float64)
        x = self.origin[0] + (cols.double() + jitter[:, 0]) * self.cell
        y = self.origin[1] + (rows.double() + jitter[:, 1]) * self.cell
        return torch.stack([x, y], 1).float().to(device)
