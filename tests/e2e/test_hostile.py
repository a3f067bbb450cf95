"""A hostile member of the team, with its own credentials, cannot hurt the honest robots: each
named attack (services/learner/attacks.py) run over Zenoh leaves the honest robots' final
val_bce within 10% of a clean run's, the lies counted as refused, and the run ends by itself."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e

ROBOTS, HOSTILE = 4, 3  # every honest robot has three neighbours: a liar among them is an outlier
ARGS = ["up", "--preset", "smoke", "--robots", str(ROBOTS), "--rounds", "40", "--no-observer",
        "--set", "learner.silent_after_s=10"]


def honest_mean(run_dir, *extra) -> tuple[float, dict]:
    proc = subprocess.run([*SWARMMAP, *ARGS, "--run-dir", str(run_dir), *extra], capture_output=True, text=True,
                          timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    learners = json.loads((run_dir / "summary.json").read_text())["learners"]
    honest = [learners[str(r)] for r in range(ROBOTS) if r != HOSTILE]
    return sum(v["final_val_bce"] for v in honest) / len(honest), learners


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return honest_mean(tmp_path_factory.mktemp("clean") / "run")[0]


def attacked(tmp_path, attack: str) -> dict:
    mean, learners = honest_mean(tmp_path / attack, "--set", f"faults.attack={attack}", "--set", f"faults.attackers=[{HOSTILE}]")
    return {"mean": mean, "learners": learners}


def test_a_member_that_lies_at_random_is_refused_and_changes_little(tmp_path, clean):
    run = attacked(tmp_path, "ratchet")
    assert run["mean"] < 1.1 * clean, (run["mean"], clean)
    assert all(run["learners"][str(r)]["refused"] > 0 for r in range(ROBOTS) if r != HOSTILE)
    logs = "".join((tmp_path / "ratchet" / "logs" / f"learner-{r}.log").read_text() for r in range(ROBOTS))
    assert "HOSTILE: it attacks its neighbours (ratchet)" in logs and "the round's spread" in logs


@pytest.mark.faults
@pytest.mark.parametrize("attack", ["signflip", "scale", "noise", "stall", "equivocate"])
def test_every_named_attack_leaves_the_honest_robots_within_10_percent_of_a_clean_run(tmp_path, clean, attack):
    run = attacked(tmp_path, attack)
    assert run["mean"] < 1.1 * clean, (attack, run["mean"], clean)


@pytest.mark.faults
def test_a_bnn_member_that_claims_false_certainty_cannot_pull_sigma_consensus(tmp_path):
    bnn = ["--set", "learner.model=bnn", "--set", "learner.model_shape=[2,64,32,32,1]", "--set", "learner.consensus=sigma"]
    clean, _ = honest_mean(tmp_path / "clean", *bnn)
    lied, _ = honest_mean(tmp_path / "sigma", *bnn, "--set", "faults.attack=sigma", "--set", f"faults.attackers=[{HOSTILE}]")
    assert lied < 1.1 * clean, (lied, clean)
