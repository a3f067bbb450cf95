"""How well a run's learned maps match its ground truth, over the cells the robots observed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from swarmmap.shared.learning.models import predict
from swarmmap.shared.learning.networks import load_model
from swarmmap.shared.world.grid import OccupancyGrid


def observed_agreement(run_dir: Path, robot: int, near_m: float = 0.15) -> float:
    """Share of ground-truth cells within ``near_m`` of any robot's training point where the
    robot's model (p > 0.5) agrees with the ground truth."""
    gt = np.load(run_dir / "groundtruth.npz")
    grid = OccupancyGrid(gt["grid"], float(gt["resolution"]), tuple(gt["origin"]))
    seen = np.zeros(grid.grid.shape, bool)
    for f in sorted((run_dir / "data").glob("robot-*.npz")):
        r, c, inside = grid.cells(np.load(f)["points"])
        seen[r[inside], c[inside]] = True
    k = max(1, int(round(near_m / grid.resolution)))
    seen = ndimage.binary_dilation(seen, iterations=k)
    pts, shape = grid.centres()
    model = load_model(run_dir / "models" / f"robot-{robot}.pt")
    pred = predict(model, pts).reshape(shape) > 0.5
    return float((pred == (grid.grid > 0))[seen].mean())
