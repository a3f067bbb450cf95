"""What an exploring learner counts as observed: the cells holding its own training points and the
cells its teammates said they have data on (the prior's coverage), on its goal map's grid."""

from __future__ import annotations

import numpy as np

from swarmmap.services.learner.explorer import observed
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.unseen import Coverage


def test_observed_cells_are_its_own_points_and_what_its_teammates_covered():
    grid = OccupancyGrid(np.zeros((20, 30), np.uint8), 0.1, (-1.0, 0.0))  # 3 m x 2 m
    centres, _ = grid.centres()
    mine = np.array([[-0.95, 0.05], [1.95, 1.95]])
    alone = observed(grid, mine, centres, None)
    assert alone.sum() == 2 and alone[0, 0] and alone[19, 29]
    cover = Coverage((-1.0, 0.0, 2.0, 2.0), margin=0.4, points=np.zeros((0, 2)))
    cover.others[:, : cover.shape[1] // 2] = True  # a teammate has data on the west half (x < 0.5)
    team = observed(grid, mine, centres, cover)
    assert team[:, centres[:30, 0] < 0.4].all() and not team[:, (centres[:30, 0] > 0.6) & (centres[:30, 0] < 1.9)].any()
