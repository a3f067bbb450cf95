"""A robot's budget: its parsing, and the control groups it makes, on folders laid out as cgroup v1
and v2 lay them out (the real ones: tests/e2e/test_budget.py)."""

from __future__ import annotations

import os

import pytest

from swarmmap.services.learner.fitting import fit
from swarmmap.services.up.budget import Cgroups, MiB, needs, refuse_if_short
from swarmmap.shared.run.config import ConfigError, resolve
from swarmmap.shared.run.limits import Limits, own_limits
from swarmmap.shared.run.sections import Budget, parse_budget


def test_a_budget_is_memory_and_cpus_and_a_bad_one_is_refused_naming_the_field():
    assert parse_budget("512M,0.5") == Budget(512 * 1024**2, 0.5)
    assert parse_budget(" 1.5G , 2 ") == Budget(int(1.5 * 1024**3), 2.0)
    assert parse_budget("700MiB,1") == Budget(700 * 1024**2, 1.0)
    for bad, why in [("512M", "is no \"MEMORY,CPUS\""), ("lots,1", "is no"), ("1M,1", "at least 32M"), ("1G,0", "between 0.01")]:
        with pytest.raises(ConfigError, match=f"up.budget: .*{why}"):
            resolve({"up": {"budget": bad}}, preset="smoke", environ={})


def test_a_budget_for_every_robot_or_one_each():
    cfg = resolve({"robots": 3, "up": {"budget": "512M,0.5;1G,1;384M,0.25"}}, preset="smoke", environ={})
    assert [cfg.budget(i) for i in range(3)] == [Budget(512 * MiB, 0.5), Budget(1024 * MiB, 1.0), Budget(384 * MiB, 0.25)]
    assert resolve({"robots": 3, "up": {"budget": "1G,2"}}, preset="smoke", environ={}).budget(2) == Budget(1024 * MiB, 2.0)
    assert resolve({"robots": 3}, preset="smoke", environ={}).budget(0) is None
    with pytest.raises(ConfigError, match="gives 2 budgets for 3 robot"):
        resolve({"robots": 3, "up": {"budget": "512M,0.5;1G,1"}}, preset="smoke", environ={})


def test_a_process_reads_its_own_limits_from_its_control_groups(tmp_path):
    """v1 (the memory and cpu hierarchies, the tightest of the group and its parents) and v2, and a
    container's (its group at the hierarchy's root, the path in /proc/self/cgroup not there)."""
    proc = tmp_path / "cgroup"
    proc.write_text("12:memory:/run/robot-0\n4:cpu,cpuacct:/run/robot-0\n1:name=systemd:/x\n")
    mem, cpu = tmp_path / "memory" / "run", tmp_path / "cpu,cpuacct" / "run"
    (mem / "robot-0").mkdir(parents=True)
    (cpu / "robot-0").mkdir(parents=True)
    (mem / "memory.limit_in_bytes").write_text(str(400 * MiB))
    (mem / "robot-0" / "memory.limit_in_bytes").write_text(str(512 * MiB))
    (tmp_path / "memory" / "memory.limit_in_bytes").write_text("9223372036854771712")  # (v1's "none")
    (cpu / "robot-0" / "cpu.cfs_quota_us").write_text("50000")
    (cpu / "robot-0" / "cpu.cfs_period_us").write_text("100000")
    assert own_limits(proc, tmp_path) == Limits(400 * MiB, 0.5)
    (tmp_path / "v2").mkdir()
    (tmp_path / "v2" / "memory.max").write_text(str(300 * MiB))
    (tmp_path / "v2" / "cpu.max").write_text("max 100000")
    proc.write_text("0::/docker/abc\n")  # (inside a container: its own group is the root)
    assert own_limits(proc, tmp_path / "v2") == Limits(300 * MiB, None)
    proc.write_text("")
    assert own_limits(proc, tmp_path) == Limits()


def test_a_learner_fits_its_budget_and_says_what_it_traded():
    cfg = resolve({"robots": 2, "learner": {"torch_threads": 4}, "up": {"budget": "2G,3;512M,0.5"}}, preset="smoke",
                  environ={})
    fitted, budget, traded = fit(cfg, 1, Limits(400 * MiB, None))
    assert budget == Limits(400 * MiB, 0.5)  # the tighter of the stated budget and the group's
    assert fitted.learner.torch_threads == 1 and fitted.zenoh.shared_memory is False
    assert any("torch threads 4 -> 1" in t for t in traded) and any("shared memory off" in t for t in traded)
    assert cfg.learner.torch_threads == 4  # (the run's config is not changed)
    fitted, _, traded = fit(cfg, 0, Limits())
    assert fitted.learner.torch_threads == 3
    unbudgeted = resolve({}, preset="smoke", environ={})
    assert fit(unbudgeted, 0, Limits()) == (unbudgeted, Limits(), [])


def test_a_budget_that_cannot_hold_the_learner_is_refused_naming_the_smallest_that_fits():
    """What a robot needs is measured (a probe process builds the run's network and node and runs it)."""
    cfg = resolve({"robots": 2}, preset="smoke", environ={})
    need = needs(cfg, [16.4, 14.7], 0, (6.9, 6.5), router=False)
    assert 150 * MiB < need["learner"] < 600 * MiB and need["total"] == need["learner"] + need["lidar"] + need["libraries"]
    bigger = needs(resolve({"robots": 2, "learner": {"model_shape": [2, 512, 512, 512, 1]}}, preset="smoke", environ={}),
                   [16.4, 14.7], 0, (6.9, 6.5), router=True)
    assert bigger["learner"] > need["learner"] and "router" in bigger
    exploring = resolve({"robots": 2, "explore": {"policy": "frontier"}}, preset="smoke", environ={})
    w = exploring.world  # an exploring robot keeps every leg's scans, up to its distance budget: not its planned path's
    scans = int(exploring.explore.distance_m / w.speed_mps * w.lidar_rate_hz) + 1
    assert needs(exploring, [16.4, 14.7], 0, (6.9, 6.5), router=False)["points"] == \
        scans * w.lidar_beams * (exploring.lidar.samples_per_beam + 1)
    refuse_if_short([Budget(2 * 1024 * MiB, 1.0)] * 2, need)
    with pytest.raises(ConfigError, match=r"robot 1's budget \(256 MiB, 0.5 CPU\) cannot hold .* The smallest budget "
                                          r"that fits: --budget \d+M,0.5") as refused:
        refuse_if_short([Budget(2 * 1024 * MiB, 1.0), Budget(256 * MiB, 0.5)], need)
    least = int(str(refused.value).split("--budget ")[1].split("M")[0])
    assert need["total"] * 1.05 <= least * MiB < need["total"] * 1.05 + 32 * MiB  # (room for a measurement again)


def v1_root(tmp_path):
    """A cgroup v1 root: the memory, cpu and cpuacct hierarchies' files a group has (as the kernel makes them)."""
    for hierarchy, files in {"memory": ["memory.limit_in_bytes"], "cpu": ["cpu.cfs_quota_us"],
                             "cpuacct": ["cpuacct.usage"]}.items():
        (tmp_path / hierarchy).mkdir()
        for f in files:
            (tmp_path / hierarchy / f).write_text("0\n")
    return tmp_path


def test_v1_groups_hold_each_robot_to_its_budget_and_report_its_peak(tmp_path):
    groups = Cgroups("run-1", [Budget(512 * 1024**2, 0.5)] * 2, root=v1_root(tmp_path))
    assert not groups.v2
    memory, cpu = tmp_path / "memory" / "swarmmap-run-1" / "robot-1", tmp_path / "cpu" / "swarmmap-run-1" / "robot-1"
    assert (memory / "memory.limit_in_bytes").read_text() == str(512 * 1024**2)
    assert (cpu / "cpu.cfs_quota_us").read_text() == "50000" and (cpu / "cpu.cfs_period_us").read_text() == "100000"
    groups.joiner(1)()  # (here: the test's own pid, written where the kernel would move it)
    assert (memory / "tasks").read_text() == str(os.getpid()) == (cpu / "tasks").read_text()
    (memory / "memory.max_usage_in_bytes").write_text(str(300 * 1024**2))
    (memory / "memory.usage_in_bytes").write_text(str(200 * 1024**2))
    (memory / "memory.failcnt").write_text("7\n")
    (memory / "memory.oom_control").write_text("oom_kill_disable 0\nunder_oom 0\noom_kill 2\n")
    (tmp_path / "cpuacct" / "swarmmap-run-1" / "robot-1" / "cpuacct.usage").write_text("12500000000")
    assert groups.usage()[1] == {"peak_memory_bytes": 300 * 1024**2, "memory_bytes_now": 200 * 1024**2, "cpu_s": 12.5,
                                 "oom_kills": 2, "limit_hits": 7}
    report = groups.report(wall_s=25.0)
    assert report["robots"]["1"]["peak_share"] == pytest.approx(300 / 512, abs=1e-4) and report["robots"]["1"]["cpus_used"] == 0.5


def test_v2_groups_use_memory_max_and_cpu_max(tmp_path):
    (tmp_path / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    (tmp_path / "cgroup.subtree_control").write_text("")
    groups = Cgroups("r", [Budget(256 * 1024**2, 1.5)], root=tmp_path)
    g = tmp_path / "swarmmap-r" / "robot-0"
    assert groups.v2 and (g / "memory.max").read_text() == str(256 * 1024**2) and (g / "cpu.max").read_text() == "150000 100000"
    assert (tmp_path / "swarmmap-r" / "cgroup.subtree_control").read_text() == "+memory +cpu"
    (g / "memory.peak").write_text("1000")
    (g / "cpu.stat").write_text("usage_usec 2000000\nuser_usec 1\n")
    (g / "memory.current").write_text("900")
    (g / "memory.events").write_text("low 0\nhigh 0\nmax 3\noom 0\noom_kill 0\n")
    assert groups.usage() == {0: {"peak_memory_bytes": 1000, "memory_bytes_now": 900, "cpu_s": 2.0, "oom_kills": 0,
                                  "limit_hits": 3}}


def test_where_no_group_can_be_made_the_run_is_refused_saying_why(tmp_path):
    with pytest.raises(ConfigError, match="up.budget: no control group for the robots' budget could be made .*neither cgroup v2"):
        Cgroups("r", [Budget(256 * 1024**2, 1.0)], root=tmp_path)
