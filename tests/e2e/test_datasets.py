"""End to end on a real robot's log: the Intel Research Lab's CARMEN log as a team of four, and the
same log converted to a rosbag2 in MCAP."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from swarmmap.shared.run.config import resolve
from swarmmap.shared.world.datasets import read_log, write_rosbag
from swarmmap.shared.world.sensing import beam_samples
from swarmmap.shared.world.teams import make_team
from tests.conftest import KIT_DATA, SWARMMAP, clean_env

pytestmark = pytest.mark.e2e
INTEL = KIT_DATA / "carmen" / "intel-corrected.log.gz"
ARGS = ("--preset", "smoke", "--robots", "4", "--rounds", "30", "--no-observer")


def up(*args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([*SWARMMAP, "up", *args], capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def intel(tmp_path_factory):
    if not INTEL.exists():
        pytest.skip("kit data ../shared/data/carmen not present")
    base = tmp_path_factory.mktemp("intel")
    up("--dataset", str(INTEL), *ARGS, "--run-dir", str(base / "carmen"))
    bag = write_rosbag(read_log(INTEL), base / "intel-bag")  # LaserScan + odometry, as a robot would record them
    up("--dataset", str(next(bag.glob("*.mcap"))), *ARGS, "--run-dir", str(base / "mcap"))
    return base


def test_a_log_trains_a_team_scored_on_held_out_scans(intel):
    run_dir = intel / "carmen"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["reference"]["kind"] == "log-odds grid of the training scans"
    for v in summary["learners"].values():
        assert v["finished"] and v["final_val_bce"] < 0.8 * v["first_val_bce"]
    assert (run_dir / "overview.png").stat().st_size > 10_000
    # The world served the held-out scans' beams as the validation set and the log-odds grid of
    # the training scans as the reference, over every hit and pose of the log.
    cfg = resolve(config_file=run_dir / "config.yaml", environ={})
    w, beams = cfg.world, cfg.labelling()
    team = make_team([read_log(INTEL)], 4, max_range=w.lidar_max_range_m, resolution=w.grid_resolution_m,
                     holdout_every=w.dataset_holdout_every, margin=w.dataset_margin_m,
                     samples_per_beam=beams.samples_per_beam, occupied_depth=beams.occupied_depth_m, val_beams=w.val_beams)
    with np.load(run_dir / "groundtruth.npz") as gt:
        assert np.array_equal(gt["val_points"], team.val_points) and np.array_equal(gt["val_labels"], team.val_labels)
        assert np.array_equal(gt["reference"], team.reference.probability())
        assert gt["grid"].shape == team.shape
    world_log = (run_dir / "logs" / "world-0.log").read_text()
    assert "robot 3: scans 683-909" in world_log and "held-out validation set" in world_log
    # Each robot trained on exactly its segment's training scans, through the sensor model with
    # nothing added (real data): the same points the beams give.
    for i, robot in enumerate(team.robots):
        want = [beam_samples(team.scan(i, k)[1][:2], *team.scan(i, k)[2:], team.max_range, beams.samples_per_beam,
                             beams.occupied_depth_m) for k in range(len(robot.train))]
        with np.load(run_dir / "data" / f"robot-{i}.npz") as got:
            assert len(got["labels"]) == sum(len(lab) for _, lab in want)
            assert got["labels"].sum() == sum(lab.sum() for _, lab in want)


def test_the_same_log_as_an_mcap_bag_learns_the_same(intel):
    a = json.loads((intel / "carmen" / "summary.json").read_text())
    b = json.loads((intel / "mcap" / "summary.json").read_text())
    assert b["ok"]
    mean = [np.mean([v["final_val_bce"] for v in s["learners"].values()]) for s in (a, b)]
    assert mean[1] == pytest.approx(mean[0], rel=0.05)
    assert b["reference"]["val_bce"] == pytest.approx(a["reference"]["val_bce"], rel=0.01)


def test_scores_of_a_dataset_run_sit_beside_the_log_odds_grid(intel):
    proc = subprocess.run([*SWARMMAP, "experiment", "score", str(intel / "carmen"), "--ensemble"], capture_output=True,
                          text=True, timeout=300, env=clean_env())
    assert proc.returncode == 0, proc.stderr
    assert "log-odds grid of the training scans (held-out beams)" in proc.stdout
    doc = json.loads((intel / "carmen" / "scores" / "scores.json").read_text())
    summary = json.loads((intel / "carmen" / "summary.json").read_text())
    assert doc["reference"]["nll"] == pytest.approx(summary["reference"]["val_bce"], rel=1e-3)
    assert 0 < doc["ensemble"]["nll"] < 1 and 0.5 < doc["ensemble"]["accuracy"] <= 1


def test_a_dataset_that_cannot_be_read_is_refused_before_anything_starts(tmp_path):
    (tmp_path / "notes.log").write_text("ODOM 0 0 0 0 0 0 0 nohost 0\n")
    for path, why in ((tmp_path / "missing.log.gz", "no such file"), (tmp_path / "notes.log", "no FLASER or ROBOTLASER1")):
        proc = subprocess.run([*SWARMMAP, "up", "--dataset", str(path), "--run-dir", str(tmp_path / "run")],
                              capture_output=True, text=True, timeout=120, env=clean_env())
        assert proc.returncode == 2 and f"world.dataset: {path}: {why}" in proc.stderr, proc.stderr
        assert not (tmp_path / "run").exists()
