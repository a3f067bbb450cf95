"""What a learner leaves in the run directory: its model, maps and training points.

``models/robot-<i>.pt`` (the final model), ``data/robot-<i>.npz`` (its training points) and its
learned map at the ground truth's resolution (``learner.map_resolution_m`` when set), written
by :func:`swarmmap.shared.run.mapfiles.save_learned_map`: ``maps/robot-<i>.npz`` (mean, std where
the model has one, origin, resolution), ``maps/robot-<i>-mean.png`` and ``-std.png`` on the
viewer's scales, and the ROS map ``maps/robot-<i>.yaml`` + ``.pgm`` (and ``-std.yaml`` +
``-std.pgm``), which ``swarmmap up --floorplan`` loads back.
"""

from __future__ import annotations

import io
import logging
import time

import numpy as np

from swarmmap.shared.learning.bnn import predict_mean_std
from swarmmap.shared.learning.models import StochasticNet
from swarmmap.shared.learning.networks import save_model
from swarmmap.shared.run.atomic import atomic_write_bytes
from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.run.mapfiles import save_learned_map
from swarmmap.shared.wire.protocol import WorldMap
from swarmmap.shared.world.grid import OccupancyGrid

log = logging.getLogger("learner")


def write_outputs(cfg: RunConfig, robot: int, model, world: WorldMap, points: np.ndarray, labels: np.ndarray) -> None:
    """The robot's training points, its model and its learned map's files, each written atomically."""
    run_dir, t0 = cfg.run_dir, time.perf_counter()
    buf = io.BytesIO()
    np.savez_compressed(buf, points=points, labels=labels)
    atomic_write_bytes(run_dir / "data" / f"robot-{robot}.npz", buf.getvalue())
    save_model(model, run_dir / "models" / f"robot-{robot}.pt", robot=robot, rounds=cfg.learner.rounds,
               run_id=cfg.run_id)
    maps = learned_maps(cfg, model, world)
    save_learned_map(run_dir / "maps", f"robot-{robot}", maps, cfg.std_max())
    log.info("robot %d: maps of %d x %d cells at %.3f m written to %s in %.1f s", robot, *maps["mean"].shape[::-1],
             maps["resolution"], run_dir / "maps", time.perf_counter() - t0)


def learned_maps(cfg: RunConfig, model, world: WorldMap) -> dict[str, np.ndarray]:
    """The model's mean (and, for a stochastic model, std) map over the ground truth's cells, from
    ``learner.mc_samples`` passes."""
    grid = OccupancyGrid(world.grid.numpy(), world.resolution, tuple(world.origin))
    res = cfg.learner.map_resolution_m or grid.resolution
    pts, (h, w) = grid.centres(res)
    mean, std = predict_mean_std(model, pts.astype(np.float32), samples=cfg.learner.mc_samples)
    maps = {"mean": mean.reshape(h, w), "origin": np.asarray(grid.origin, np.float64), "resolution": np.float64(res)}
    if isinstance(model, StochasticNet):
        maps["std"] = std.reshape(h, w)
    return maps
