"""What a learner leaves in the run directory: its model, map and training points."""

from __future__ import annotations

import io

import numpy as np

from swarmmap.shared.atomic import atomic_write_bytes, save_png
from swarmmap.shared.bnn import predict_mean_std
from swarmmap.shared.config import RunConfig
from swarmmap.shared.floorplan import OccupancyGrid
from swarmmap.shared.models import StochasticNet, save_model
from swarmmap.shared.protocol import WorldMap


def write_outputs(cfg: RunConfig, robot: int, model, world: WorldMap, points: np.ndarray, labels: np.ndarray) -> None:
    """The model checkpoint, its mean map PNG (and for a BNN its std map PNG and both as .npz)
    and the robot's training points, written atomically."""
    run_dir = cfg.run_dir
    buf = io.BytesIO()
    np.savez_compressed(buf, points=points, labels=labels)
    atomic_write_bytes(run_dir / "data" / f"robot-{robot}.npz", buf.getvalue())
    save_model(model, run_dir / "models" / f"robot-{robot}.pt", robot=robot, rounds=cfg.learner.rounds,
               run_id=cfg.run_id)
    grid = OccupancyGrid(world.grid.numpy(), world.resolution, tuple(world.origin))
    pts, (h, w) = grid.centres(cfg.learner.map_resolution_m)
    mean, std = predict_mean_std(model, pts, samples=cfg.learner.mc_samples)
    save_png(run_dir / "maps" / f"robot-{robot}-mean.png", mean.reshape(h, w))
    if isinstance(model, StochasticNet):
        # Darker = more uncertain, on a fixed scale (std of a probability is at most 0.5).
        save_png(run_dir / "maps" / f"robot-{robot}-std.png", np.clip(std.reshape(h, w) / 0.5, 0, 1))
        buf = io.BytesIO()
        np.savez_compressed(buf, mean=mean.reshape(h, w), std=std.reshape(h, w), origin=np.asarray(grid.origin),
                            resolution=cfg.learner.map_resolution_m)
        atomic_write_bytes(run_dir / "maps" / f"robot-{robot}.npz", buf.getvalue())
