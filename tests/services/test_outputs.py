"""What a learner leaves: its model, training points and maps at the ground truth's resolution, for every model."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from swarmmap.services.learner.outputs import write_outputs
from swarmmap.services.world.simulation import build_plan, world_map_message
from swarmmap.shared.learning.networks import build_network
from swarmmap.shared.run.config import resolve


@pytest.fixture(scope="module")
def world():
    cfg = resolve({"world": {"val_scans": 5}}, preset="smoke", environ={})
    grid = build_plan(cfg).occupancy(cfg.world.grid_resolution_m)
    return world_map_message(cfg, grid), grid


def outputs(tmp_path, world, **learner):
    message, _ = world
    cfg = resolve({"run_dir": str(tmp_path), "learner": {"mc_samples": 4, **learner}}, preset="smoke", environ={})
    model = build_network(cfg.network(), message.bounds, cfg.seed)
    points, labels = np.zeros((10, 2), np.float32), np.zeros(10, np.float32)
    write_outputs(cfg, 1, model, message, points, labels)
    return tmp_path


@pytest.mark.parametrize("model", ["fourier", "bnn", "dropout"])
def test_every_model_saves_its_maps_on_the_ground_truths_cells(tmp_path, world, model):
    run_dir = outputs(tmp_path, world, model=model)
    _, grid = world
    with np.load(run_dir / "maps" / "robot-1.npz") as z:
        assert z["mean"].shape == grid.grid.shape, "the ground truth's resolution, not a coarser one"
        assert float(z["resolution"]) == pytest.approx(grid.resolution)
        np.testing.assert_allclose(z["origin"], grid.origin)
        assert ("std" in z.files) == (model != "fourier")
        if model != "fourier":
            assert z["std"].shape == grid.grid.shape and z["std"].max() > 0
    doc = yaml.safe_load((run_dir / "maps" / "robot-1.yaml").read_text())
    assert doc["resolution"] == pytest.approx(grid.resolution) and doc["origin"][:2] == pytest.approx(list(grid.origin))
    assert (run_dir / "maps" / "robot-1-std.pgm").exists() == (model != "fourier")
    assert (run_dir / "models" / "robot-1.pt").exists() and (run_dir / "data" / "robot-1.npz").exists()


def test_a_set_map_resolution_is_kept(tmp_path, world):
    run_dir = outputs(tmp_path, world, map_resolution_m=0.1)
    _, grid = world
    with np.load(run_dir / "maps" / "robot-1.npz") as z:
        assert float(z["resolution"]) == pytest.approx(0.1)
        assert z["mean"].shape == tuple(n // 2 for n in grid.grid.shape)  # cells of 0.1 m whose centres lie on the map
