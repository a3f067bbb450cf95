"""``swarmmap up --budget``: every robot's services in a real control group of this host (needs
root), their peaks in summary.json; a budget its learner cannot live in ends the run naming it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import pytest

from tests.conftest import SWARMMAP, clean_env, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.faults]


def up(run_dir, budget: str) -> subprocess.CompletedProcess:
    return subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--robots", "2", "--rounds", "20", "--budget", budget,
                           "--run-dir", str(run_dir)], capture_output=True, text=True, timeout=600, env=clean_env())


def test_robots_run_in_their_budget_and_one_too_small_ends_the_run_naming_it(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("control groups are made by root here (or on a delegated subtree)")
    ok = up(tmp_path / "ok", "1G,0.8")
    assert ok.returncode == 0, ok.stderr[-3000:]
    summary = json.loads((tmp_path / "ok" / "summary.json").read_text())
    budget = summary["budget"]
    assert budget["memory_bytes"] == 1024**3 and budget["cpus"] == 0.8 and set(budget["robots"]) == {"0", "1"}
    for robot, used in budget["robots"].items():
        # a learner (torch) and a lidar streamer: hundreds of MB, under the limit; CPU time spent, at most the quota's
        assert 150 * 1024**2 < used["peak_memory_bytes"] < 1024**3 and used["oom_kills"] == 0, (robot, used)
        assert 0 < used["cpus_used"] <= 0.8 * 1.05, (robot, used)
    assert "robot 0's budget: peak memory" in ok.stderr
    small = up(tmp_path / "small", "250M,1")
    assert small.returncode == 1
    summary = json.loads((tmp_path / "small" / "summary.json").read_text())
    assert "was killed at robot" in summary["reason"] and "memory budget (250 MiB, 1 CPU)" in summary["reason"], summary
    assert all(s["restarts"] == 0 for s in summary["services"].values())  # it would only be killed again
    assert not groups_of(summary["run_id"])  # the run's groups are gone


def groups_of(run_id: str) -> list[Path]:
    """The control groups of run ``run_id`` on this host (v2, v1's hierarchies)."""
    roots = [Path("/sys/fs/cgroup"), *(Path("/sys/fs/cgroup") / h for h in ("memory", "cpu", "cpuacct"))]
    return [r / f"swarmmap-{run_id}" for r in roots if (r / f"swarmmap-{run_id}").exists()]


def test_a_launcher_killed_with_sigkill_leaves_no_control_group_behind(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("control groups are made by root here (or on a delegated subtree)")
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([*SWARMMAP, "up", "--preset", "smoke", "--robots", "2", "--budget", "1G,1", "--run-id",
                             "budget-kill9", "--run-dir", str(run_dir)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=clean_env())
    try:
        assert wait_until(lambda: bool(groups_of("budget-kill9")) and (run_dir / "logs" / "learner-0.log").exists(), 120)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert wait_until(lambda: not groups_of("budget-kill9"), 60), groups_of("budget-kill9")
    assert "removed" in (run_dir / "logs" / "budget-guard.log").read_text()
