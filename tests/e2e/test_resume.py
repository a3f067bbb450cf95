"""Checkpoints: a team started again on the run directory of a crashed run (``--resume``)
resumes from its checkpoints and ends exactly where the uninterrupted run ended; nothing already
written is lost, and no metrics row is written twice. (Runs interrupted for real, and the
run-directory rules: tests/e2e/test_rundirs.py.)"""

from __future__ import annotations

import csv
import shutil
import subprocess

import pytest
import torch

from swarmmap.shared.learning.networks import load_model
from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e


def up(run_dir, *extra):
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--rounds", "20",
                           "--set", "learner.checkpoint_every=10", "--run-dir", str(run_dir), *extra],
                          capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]


# A fault trial (a run stopped at a round and resumed from its checkpoints), run with the others (make test-faults).
@pytest.mark.faults
def test_resumed_run_ends_where_the_uninterrupted_one_did(tmp_path):
    # The Bayesian network (the paper's model): its checkpoints hold rho beside the means, and the
    # optimiser's state of both; a FourierNet's are a subset of that.
    model = "bnn"
    a, b = tmp_path / "a", tmp_path / "b"
    up(a, "--set", f"learner.model={model}")
    assert sorted(p.name for p in (a / "checkpoints").iterdir()) == [
        "robot-0-data.pt", "robot-0.pt", "robot-1-data.pt", "robot-1.pt", "robot-2-data.pt", "robot-2.pt"]
    assert torch.load(a / "checkpoints" / "robot-0.pt", weights_only=True)["round"] == 10
    # B: the run directory as a crash of every process after round 15 would leave it: checkpoints of
    # round 10, metrics up to round 15, no models and no summary.
    shutil.copytree(a, b)
    shutil.rmtree(b / "models")
    (b / "summary.json").unlink()
    rows = (b / "metrics.csv").read_text().splitlines(keepends=True)
    (b / "metrics.csv").write_text("".join([rows[0]] + [r for r in rows[1:] if int(r.split(",")[1]) <= 15]))
    (b / "checkpoints" / ".robot-1.pt.x1y2.tmp").write_bytes(b"half a checkpoint")  # a learner killed while writing
    before = list(csv.DictReader((b / "metrics.csv").open()))
    up(b, "--set", f"learner.model={model}", "--resume")
    for robot in range(3):
        log = (b / "logs" / f"learner-{robot}.log").read_text()
        assert "resuming from" in log and "at round 10" in log
        sa = load_model(a / "models" / f"robot-{robot}.pt").state_dict()
        sb = load_model(b / "models" / f"robot-{robot}.pt").state_dict()
        for name in sa:
            torch.testing.assert_close(sa[name], sb[name], rtol=0, atol=1e-6)
    after = list(csv.DictReader((b / "metrics.csv").open()))
    assert after[: len(before)] == before and len(after) > len(before)
    keys = [(r["robot"], r["round"], r["final"]) for r in after]
    assert len(keys) == len(set(keys)), "rows written twice after the resume"
    assert sorted(keys) == sorted((r["robot"], r["round"], r["final"]) for r in csv.DictReader((a / "metrics.csv").open()))
    assert not list((b / "checkpoints").glob("*.tmp")), "a leftover .tmp was kept"
    # The first row after the resume is the resumed model's, not an untrained one's.
    resumed = [r for r in after[len(before):] if r["robot"] == "0"][0]
    same_round = [r for r in before if r["robot"] == "0" and r["round"] == resumed["round"]]
    assert not same_round or abs(float(same_round[0]["val_bce"]) - float(resumed["val_bce"])) < 1e-4


def test_unreadable_checkpoint_is_named(tmp_path):
    run = tmp_path / "c"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "robot-1.pt").write_bytes(b"not a checkpoint")
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--rounds", "5", "--resume",
                           "--run-dir", str(run)], capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 1
    assert "cannot read checkpoint" in (run / "logs" / "learner-1.log").read_text()


def test_a_run_of_other_settings_is_refused_and_nothing_is_overwritten(tmp_path):
    run = tmp_path / "run"
    prepared = subprocess.run([*SWARMMAP, "prepare", "--preset", "smoke", "--run-dir", str(run)], capture_output=True, text=True,
                              timeout=120, env=clean_env())
    assert prepared.returncode == 0, prepared.stderr
    kept = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--seed", "7", "--resume", "--run-dir", str(run)],
                          capture_output=True, text=True, timeout=120, env=clean_env())
    assert proc.returncode == 2 and "holds a run with other settings (seed 0 there, 7 here)" in proc.stderr
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == kept, "the run's files were changed"
