"""Exploration end to end: a team that chooses its goals by its maps' uncertainty covers the plan
from the starts it was given, never enters a wall, and leaves exploration.csv, goals.csv and the
summary's exploration section, consistent with each other."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from swarmmap.services.world.exploring import BODY_RADIUS_M
from swarmmap.shared.world.explore import EXPLORATION_COLUMNS, GOAL_COLUMNS, exploration_summary, read_exploration
from swarmmap.shared.world.grid import OccupancyGrid
from tests.conftest import SWARMMAP, clean_env, recording_entities

pytestmark = pytest.mark.e2e
STARTS = "1,1;1,3.2;6,5.5"


def test_an_uncertainty_team_covers_the_plan_from_its_starts_and_never_enters_a_wall(tmp_path):
    run_dir = tmp_path / "run"
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "quickstart", "--rounds", "60", "--explore", "uncertainty",
                           "--starts", STARTS, "--run-dir", str(run_dir)], capture_output=True, text=True, timeout=600,
                          env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "explored       uncertainty:" in proc.stdout and "exploration.csv" in proc.stdout
    rows = read_exploration(run_dir / "exploration.csv")
    assert (run_dir / "exploration.csv").read_text().splitlines()[0] == ",".join(EXPLORATION_COLUMNS)
    starts = np.array([[float(v) for v in p.split(",")] for p in STARTS.split(";")])
    with np.load(run_dir / "groundtruth.npz") as gt:
        truth = OccupancyGrid(gt["grid"], float(gt["resolution"]), tuple(gt["origin"]))
    clear = truth.clearance()
    for robot in range(3):
        mine = [r for r in rows if r["robot"] == robot]
        xy = np.array([(r["x"], r["y"]) for r in mine])
        assert xy[0] == pytest.approx(starts[robot]) and np.ptp(xy, axis=0).max() > 1.0, f"robot {robot} never drove"
        r, c, inside = truth.cells(xy)
        assert inside.all() and (clear[r, c] >= BODY_RADIUS_M).all(), f"robot {robot} inside or against a wall"
        # (poses are taken at each scan: their chords cut the corners a robot drove between two scans)
        assert np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() == pytest.approx(mine[-1]["distance_m"], rel=0.05)
        assert not np.isnan(mine[-1]["val_bce"])
    coverage = [r["coverage"] for r in rows]
    assert coverage == sorted(coverage) and coverage[-1] >= 0.9
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["exploration"] == {**exploration_summary(rows, "uncertainty"),
                                                       "coverage_of": "the reachable free space"}
    assert summary["exploration"]["team_distance_at_coverage"]["0.9"] is not None
    goals = read_exploration(run_dir / "goals.csv", GOAL_COLUMNS)
    assert {int(g["robot"]) for g in goals} == {0, 1, 2} and [g["leg"] for g in goals] == sorted(g["leg"] for g in goals)
    assert (run_dir / "overview.png").exists()
    entities = recording_entities(run_dir / "recording.rrd")  # the Rerun recording shows the goals and planned paths
    assert all(f"/world/robots/{i}/goal/path" in entities and f"/world/robots/{i}/goal" in entities for i in range(3))
