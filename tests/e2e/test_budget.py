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


def limits_of(pid: int) -> tuple[str, int, int]:
    """The group a process is in, read from /proc/PID/cgroup (v1 here, or v2), and its memory limit
    and CPU quota (per 100 ms) as the kernel holds them."""
    lines = dict(line.split(":", 2)[1:] for line in Path(f"/proc/{pid}/cgroup").read_text().splitlines())
    if "" in lines and "memory" not in lines:  # v2
        group = Path("/sys/fs/cgroup") / lines[""].lstrip("/")
        quota = (group / "cpu.max").read_text().split()[0]
        return lines[""], int((group / "memory.max").read_text()), int(quota)
    cpu_key = next(k for k in lines if "cpu" in k.split(","))
    memory = Path("/sys/fs/cgroup/memory") / lines["memory"].lstrip("/")
    cpu = Path("/sys/fs/cgroup/cpu") / lines[cpu_key].lstrip("/")
    return lines["memory"], int((memory / "memory.limit_in_bytes").read_text()), int((cpu / "cpu.cfs_quota_us").read_text())


def service_pids(run_dir: Path, service: str) -> dict[int, int]:
    """robot -> pid of each ``service`` process of the run in ``run_dir`` (from their command lines)."""
    out = {}
    for proc in Path("/proc").iterdir():
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        words = [a.decode(errors="replace") for a in argv]
        if service in words and f"{run_dir}/config.yaml" in words and "--robot" in words:
            out[int(words[words.index("--robot") + 1])] = int(proc.name)
    return out


def test_robots_run_in_their_budget_and_one_too_small_is_refused_at_start(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("control groups are made by root here (or on a delegated subtree)")
    run_dir = tmp_path / "ok"
    proc = subprocess.Popen([*SWARMMAP, "up", "--preset", "smoke", "--robots", "2", "--rounds", "20", "--budget",
                             "1G,0.8;768M,0.5", "--run-dir", str(run_dir)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=clean_env())
    try:
        assert wait_until(lambda: len(service_pids(run_dir, "learner")) == 2 and len(service_pids(run_dir, "lidar")) == 2, 120)
        for service in ("learner", "lidar"):  # every one in its robot's group, with that robot's limits
            for robot, pid in service_pids(run_dir, service).items():
                group, memory, quota = limits_of(pid)
                assert group.endswith(f"/robot-{robot}") and "swarmmap-" in group, (service, group)
                assert (memory, quota) == ((1024**3, 80_000) if robot == 0 else (768 * 1024**2, 50_000)), (service, robot)
        assert wait_until(lambda: (run_dir / "budget.json").exists(), 30)
        live = subprocess.run([*SWARMMAP, "status", str(run_dir)], capture_output=True, text=True, timeout=60, env=clean_env())
        assert "budgets" in live.stdout and "of 768 MiB, CPU" in live.stdout, live.stdout
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    budget = summary["budget"]
    assert budget["memory_bytes"] is None and set(budget["robots"]) == {"0", "1"}  # (one each)
    for robot, used in budget["robots"].items():
        # a learner (torch) and a lidar streamer: hundreds of MB, under the limit; CPU time spent, at most the quota's
        assert 150 * 1024**2 < used["peak_memory_bytes"] < used["memory_bytes"] and used["oom_kills"] == 0, (robot, used)
        assert 0 < used["cpus_used"] <= used["cpus"] * 1.05, (robot, used)
    assert "robot 0's budget: peak memory" in err
    learner_log = (run_dir / "logs" / "learner-1.log").read_text()
    assert "robot 1's budget: 768 MiB, 0.5 CPU;" in learner_log and "Zenoh shared memory off" in learner_log
    done = subprocess.run([*SWARMMAP, "status", str(run_dir)], capture_output=True, text=True, timeout=60, env=clean_env())
    assert "robot   1  peak" in done.stdout and "of 768 MiB" in done.stdout, done.stdout

    small = up(tmp_path / "small", "250M,1")
    assert small.returncode == 2, small.stderr[-2000:]
    assert "every robot's budget (250 MiB, 1 CPU) cannot hold its services" in small.stderr
    assert "The smallest budget that fits: --budget" in small.stderr
    assert not (tmp_path / "small").exists()  # refused before anything was written or started


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
