"""The Python API's parts that need no run: overrides, and a run directory read back."""

from __future__ import annotations

import numpy as np
import pytest

from swarmmap.shared.api import RunError, config, open_run, overrides_tree
from tests.conftest import recorded_run


def test_overrides_take_sections_by_double_underscore_or_as_dicts():
    assert overrides_tree({"robots": 3, "learner__rounds": 20, "learner": {"model": "bnn"}, "world__lidar_beams": 90}) == {
        "robots": 3, "learner": {"rounds": 20, "model": "bnn"}, "world": {"lidar_beams": 90}}
    cfg = config("smoke", robots=4, learner={"rounds": 30})
    assert (cfg.robots, cfg.learner.rounds, cfg.preset) == (4, 30, "smoke")


def test_a_finished_run_reads_back_as_a_table_and_its_summary(tmp_path):
    run = open_run(recorded_run(tmp_path / "run", losses=(0.125, 0.235), rounds=60))
    m = run.metrics
    assert m.dtype.names[:4] == ("robot", "round", "wall_time_s", "val_bce") and len(m) == 6
    assert np.allclose(sorted(m["val_bce"][m["round"] == 60]), [0.125, 0.235])
    assert run.ok and run.failure is None and run.robots == [0, 1] and run.final_val_bce() == {0: 0.125, 1: 0.235}
    with pytest.raises(RunError, match="robot 0's learner wrote no map"):
        run.maps(0)
    failed = open_run(recorded_run(tmp_path / "failed", ok=False))
    assert not failed.ok and "learner 1 left before finishing" in failed.failure and "failed" in repr(failed)
