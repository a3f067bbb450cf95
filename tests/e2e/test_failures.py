"""Failures are normal: a learner killed (SIGKILL) at a random round is restarted by ``up``,
resumes from its checkpoint, rejoins its team and the run finishes as a clean run does; 30%
of Algorithm 1's messages lost changes nothing; learners on links that set the pace compress their
States; a killed launcher leaves no service behind."""

from __future__ import annotations

import json
import os
import random
import signal
import time

import pytest

from tests.conftest import wait_until
from tests.harness import final_losses, kill_at_round, leftovers, reported_round, service_pids, up

pytestmark = pytest.mark.e2e

SMOKE = ["--preset", "smoke", "--robots", "3", "--no-observer"]


@pytest.mark.faults
def test_thirty_percent_of_messages_lost_changes_nothing(tmp_path):
    short = ["--rounds", "30"]  # every round loses messages alike: 30 rounds show it as well as 60
    clean = up(tmp_path / "clean", *SMOKE, *short)
    assert clean.wait(300) == 0
    lossy = up(tmp_path / "lossy", *SMOKE, *short, "--set", "faults.link_success=0.7", "--set", "learner.resend_after_s=0.2")
    assert lossy.wait(600) == 0
    assert "injecting faults" in (tmp_path / "lossy" / "logs" / "learner-0.log").read_text()
    # Algorithm 1 waits for (resent) messages instead of going on without them: the same result.
    assert final_losses(tmp_path / "lossy") == final_losses(tmp_path / "clean")


@pytest.mark.faults
def test_learners_whose_links_set_the_pace_compress_their_states_and_say_so(tmp_path):
    """Every State and RoundComplete late by up to 0.8 s: each learner waits far longer than it
    trains, switches its States to 3-bit quant after 20 rounds (learner.slow_link_compression), says so, and the run ends near a
    clean run's val_bce."""
    short = ["--rounds", "40"]
    clean = up(tmp_path / "clean", *SMOKE, *short)
    assert clean.wait(300) == 0
    slow = up(tmp_path / "slow", *SMOKE, *short, "--set", "faults.delay_s=0.8", "--set", "learner.slow_link_compression=quant")
    assert slow.wait(600) == 0
    for i in range(3):
        log = (tmp_path / "slow" / "logs" / f"learner-{i}.log").read_text()
        assert "its links, not its training, set the pace; its States go out as quant" in log
    for r, bce in final_losses(tmp_path / "slow").items():
        assert bce < 1.1 * final_losses(tmp_path / "clean")[r], r


def test_a_killed_launcher_takes_every_service_with_it(tmp_path):
    run_dir = tmp_path / "run"
    proc = up(run_dir, *SMOKE, "--rounds", "100000")
    assert wait_until(lambda: len(service_pids(run_dir, "learner")) == 3 and (run_dir / "logs").exists(), 120, 0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert wait_until(lambda: not leftovers(run_dir), 30, 0.2), f"left running: {leftovers(run_dir)}"


def clean_kill_run(tmp_path_factory, rounds: int):
    """One clean smoke run of ``rounds`` rounds for every kill trial of the session; its directory."""
    clean_dir = tmp_path_factory.getbasetemp() / "kill-trials" / "clean"
    if not (clean_dir / "summary.json").exists():
        assert up(clean_dir, *SMOKE, "--rounds", str(rounds)).wait(600) == 0
    return clean_dir


def run_killed(run_dir, robot: int, at: int, after: float, *args: str) -> None:
    """A smoke run whose learner ``robot`` is killed ``after`` seconds after it reported round ``at``; it must end ok."""
    proc = up(run_dir, *SMOKE, *args)
    try:
        kill_at_round(run_dir, "learner", robot, at, after_s=after)
        assert proc.wait(600) == 0, (run_dir.parent / f"{run_dir.name}.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.faults
@pytest.mark.parametrize("trial", range(5))
def test_a_learner_killed_at_a_random_round_restarts_rejoins_and_the_run_finishes(tmp_path_factory, trial):
    rounds = 200
    clean_dir = clean_kill_run(tmp_path_factory, rounds)
    rng = random.Random(trial)
    robot, at, after = rng.randrange(3), rng.randrange(10, rounds - 40), rng.uniform(0, 1.5)
    run_dir = clean_dir.parent / f"trial-{trial}"
    run_killed(run_dir, robot, at, after, "--rounds", str(rounds))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["services"][f"learner-{robot}"]["restarts"] == 1
    log = (run_dir / "logs" / f"learner-{robot}.log").read_text()
    assert "resuming from" in log and f"robot {robot} done: {rounds} rounds" in log, "the restarted learner did not rejoin"
    clean = final_losses(clean_dir)
    for r, loss in final_losses(run_dir).items():
        assert abs(loss - clean[r]) <= 0.05 * clean[r], \
            f"robot {r}: {loss:.4f} against {clean[r]:.4f} clean (killed {robot} {after:.1f} s after round {at})"
    assert not leftovers(run_dir), "a service outlived the run"


@pytest.mark.faults
def test_a_learner_killed_near_the_end_replays_the_rounds_it_lost_from_its_finished_team(tmp_path_factory):
    """Killed in the last rounds, with no wait for its return (rejoin_wait_s 0): its team finishes
    without it while it restarts from its last checkpoint (smoke: every 5 rounds), fewer rounds
    back than its neighbours keep for a replay (checkpoint_every + 2), too few to jump; the
    finished neighbours send it their States of the rounds it lost, it replays them and finishes,
    and the run is ok."""
    rounds, robot = 200, 2
    clean_dir = clean_kill_run(tmp_path_factory, rounds)
    run_dir = clean_dir.parent / "near-the-end"
    run_killed(run_dir, robot, rounds - 5, 0.0, "--rounds", str(rounds), "--set", "learner.rejoin_wait_s=0")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["services"][f"learner-{robot}"]["restarts"] == 1
    log = (run_dir / "logs" / f"learner-{robot}.log").read_text()
    assert "resuming from" in log and f"robot {robot} done: {rounds} rounds" in log
    neighbours = "".join((run_dir / "logs" / f"learner-{i}.log").read_text() for i in (0, 1))
    assert f"neighbour {robot} is back at round" in neighbours, "no finished neighbour sent it the rounds it lost"
    clean = final_losses(clean_dir)
    for r, loss in final_losses(run_dir).items():
        assert loss <= 1.1 * clean[r], f"robot {r}: {loss:.4f} against {clean[r]:.4f} clean"


def final_points(run_dir) -> dict[str, int]:
    """Each robot's training points, from its final Metrics row."""
    import csv

    with (run_dir / "metrics.csv").open() as f:
        return {r["robot"]: int(r["n_points"]) for r in csv.DictReader(f) if r["final"] == "1"}


@pytest.mark.faults
def test_a_world_killed_mid_traversal_restarts_and_the_learners_take_each_scan_once(tmp_path):
    """The world killed (SIGKILL) 3 s into a traversal driven in real time: up restarts it, it
    drives from the start again, each learner drops the scans it had (counted in summary.json)
    and trains on exactly the points of a clean run."""
    args = [*SMOKE, "--rounds", "20", "--set", "world.time_scale=1"]
    clean_dir, run_dir = tmp_path / "clean", tmp_path / "run"
    assert up(clean_dir, *args).wait(600) == 0
    proc = up(run_dir, *args)
    try:
        assert wait_until(lambda: "the robots drive" in recorder_log(run_dir), 180, 0.1)
        time.sleep(3)
        os.kill(service_pids(run_dir, "world")[0], signal.SIGKILL)
        assert proc.wait(600) == 0, (tmp_path / "run.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["services"]["world-0"]["restarts"] == 1
    assert sum(v["repeated_samples"] for v in summary["learners"].values()) > 0
    assert final_points(run_dir) == final_points(clean_dir)


@pytest.mark.faults
def test_an_observer_killed_mid_run_never_fails_the_run(tmp_path):
    """The observer (optional) killed while the team trains: up says so and the run finishes ok."""
    run_dir = tmp_path / "run"
    proc = up(run_dir, "--preset", "smoke", "--robots", "3", "--observer", "--no-viewer", "--rounds", "150")
    try:
        assert wait_until(lambda: reported_round(run_dir, 0) >= 5 and service_pids(run_dir, "observer"), 300, 0.1)
        os.kill(service_pids(run_dir, "observer")[0], signal.SIGKILL)
        assert proc.wait(600) == 0, (tmp_path / "run.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert json.loads((run_dir / "summary.json").read_text())["ok"]
    assert "the run goes on without it" in (tmp_path / "run.up.log").read_text()


def recorder_log(run_dir) -> str:
    try:
        return (run_dir / "logs" / "recorder-0.log").read_text()
    except OSError:
        return ""
