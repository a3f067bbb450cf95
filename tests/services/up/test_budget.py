"""A robot's budget: its parsing, and the control groups it makes, on folders laid out as cgroup v1
and v2 lay them out (the real ones: tests/e2e/test_budget.py)."""

from __future__ import annotations

import os

import pytest

from swarmmap.services.up.budget import Cgroups
from swarmmap.shared.run.config import ConfigError, resolve
from swarmmap.shared.run.sections import Budget, parse_budget


def test_a_budget_is_memory_and_cpus_and_a_bad_one_is_refused_naming_the_field():
    assert parse_budget("512M,0.5") == Budget(512 * 1024**2, 0.5)
    assert parse_budget(" 1.5G , 2 ") == Budget(int(1.5 * 1024**3), 2.0)
    assert parse_budget("700MiB,1") == Budget(700 * 1024**2, 1.0)
    for bad, why in [("512M", "is no \"MEMORY,CPUS\""), ("lots,1", "is no"), ("1M,1", "at least 32M"), ("1G,0", "between 0.01")]:
        with pytest.raises(ConfigError, match=f"up.budget: .*{why}"):
            resolve({"up": {"budget": bad}}, preset="smoke", environ={})


def v1_root(tmp_path):
    """A cgroup v1 root: the memory, cpu and cpuacct hierarchies' files a group has (as the kernel makes them)."""
    for hierarchy, files in {"memory": ["memory.limit_in_bytes"], "cpu": ["cpu.cfs_quota_us"],
                             "cpuacct": ["cpuacct.usage"]}.items():
        (tmp_path / hierarchy).mkdir()
        for f in files:
            (tmp_path / hierarchy / f).write_text("0\n")
    return tmp_path


def test_v1_groups_hold_each_robot_to_its_budget_and_report_its_peak(tmp_path):
    groups = Cgroups("run-1", 2, Budget(512 * 1024**2, 0.5), root=v1_root(tmp_path))
    assert not groups.v2
    memory, cpu = tmp_path / "memory" / "swarmmap-run-1" / "robot-1", tmp_path / "cpu" / "swarmmap-run-1" / "robot-1"
    assert (memory / "memory.limit_in_bytes").read_text() == str(512 * 1024**2)
    assert (cpu / "cpu.cfs_quota_us").read_text() == "50000" and (cpu / "cpu.cfs_period_us").read_text() == "100000"
    groups.joiner(1)()  # (here: the test's own pid, written where the kernel would move it)
    assert (memory / "tasks").read_text() == str(os.getpid()) == (cpu / "tasks").read_text()
    (memory / "memory.max_usage_in_bytes").write_text(str(300 * 1024**2))
    (memory / "memory.oom_control").write_text("oom_kill_disable 0\nunder_oom 0\noom_kill 2\n")
    (tmp_path / "cpuacct" / "swarmmap-run-1" / "robot-1" / "cpuacct.usage").write_text("12500000000")
    assert groups.usage()[1] == {"peak_memory_bytes": 300 * 1024**2, "cpu_s": 12.5, "oom_kills": 2}
    report = groups.report(wall_s=25.0)
    assert report["robots"]["1"]["peak_share"] == pytest.approx(300 / 512, abs=1e-4) and report["robots"]["1"]["cpus_used"] == 0.5


def test_v2_groups_use_memory_max_and_cpu_max(tmp_path):
    (tmp_path / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    (tmp_path / "cgroup.subtree_control").write_text("")
    groups = Cgroups("r", 1, Budget(256 * 1024**2, 1.5), root=tmp_path)
    g = tmp_path / "swarmmap-r" / "robot-0"
    assert groups.v2 and (g / "memory.max").read_text() == str(256 * 1024**2) and (g / "cpu.max").read_text() == "150000 100000"
    assert (tmp_path / "swarmmap-r" / "cgroup.subtree_control").read_text() == "+memory +cpu"
    (g / "memory.peak").write_text("1000")
    (g / "cpu.stat").write_text("usage_usec 2000000\nuser_usec 1\n")
    (g / "memory.events").write_text("low 0\noom 0\noom_kill 0\n")
    assert groups.usage() == {0: {"peak_memory_bytes": 1000, "cpu_s": 2.0, "oom_kills": 0}}


def test_where_no_group_can_be_made_the_run_is_refused_saying_why(tmp_path):
    with pytest.raises(ConfigError, match="up.budget: no control group for the robots' budget could be made .*neither cgroup v2"):
        Cgroups("r", 1, Budget(256 * 1024**2, 1.0), root=tmp_path)
