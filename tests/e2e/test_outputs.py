"""End to end: a first run (preset quickstart) leaves maps to look at and to use, and its learned
ROS map is the floor plan of another run that finishes."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from PIL import Image

from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.world.plans import load_floorplan
from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e


def up(*args: str) -> dict:
    proc = subprocess.run([*SWARMMAP, "up", *args], capture_output=True, text=True, timeout=240, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("quickstart") / "run"
    up("--preset", "quickstart", "--rounds", "20", "--run-dir", str(run_dir))
    return run_dir


def test_a_first_run_leaves_an_overview_and_maps_with_a_std(first_run):
    overview = Image.open(first_run / "overview.png")
    assert overview.width > 1000 and overview.height > 900  # three robots' rows of four panels
    gt = np.load(first_run / "groundtruth.npz")
    inside = gt["grid"] == 0  # the rooms the robots mapped
    for robot in range(3):
        names = {p.name for p in (first_run / "maps").glob(f"robot-{robot}*")}
        assert names == {f"robot-{robot}{s}" for s in (".npz", "-mean.png", "-std.png", ".yaml", ".pgm", "-std.yaml", "-std.pgm")}
        with np.load(first_run / "maps" / f"robot-{robot}.npz") as z:
            assert z["std"].shape == gt["grid"].shape
            outside = np.zeros(inside.shape, bool)
            outside[:4], outside[-4:], outside[:, :4], outside[:, -4:] = True, True, True, True  # 20 cm no robot saw
            assert z["std"][outside].mean() > 3 * z["std"][inside].mean(), "the std is high where nobody looked"


def test_a_learned_map_is_the_floor_plan_of_a_run_that_finishes(first_run, tmp_path):
    plan = first_run / "maps" / "robot-0.yaml"
    second = tmp_path / "second"
    up("--preset", "smoke", "--robots", "2", "--rounds", "10", "--floorplan", str(plan), "--run-dir", str(second))
    summary = json.loads((second / "summary.json").read_text())
    assert summary["ok"] and all(v["finished"] and v["final_val_bce"] < v["first_val_bce"] for v in summary["learners"].values())
    # The second run's ground truth is the first run's learned map, as map_server reads it.
    learned = load_floorplan(str(plan), RunConfig().world, 0).raster
    gt = np.load(second / "groundtruth.npz")
    np.testing.assert_array_equal(gt["grid"], np.where(learned.unknown, 2, learned.grid))
    assert (second / "overview.png").exists() and (second / "maps" / "robot-1.yaml").exists()
