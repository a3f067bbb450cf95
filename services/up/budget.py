"""A robot's budget (``up.budget``, ``swarmmap up --budget MEMORY,CPUS``): every robot's services
(its lidar streamer and learner, and its router under ``--netns``) run in a Linux control group of
their own that holds them to ``MEMORY`` (bytes with K, M or G: powers of 1024) and ``CPUS`` (cores,
fractions allowed), the same for every robot.

cgroup v2 (``/sys/fs/cgroup`` with the ``memory`` and ``cpu`` controllers: ``memory.max``,
``memory.swap.max`` 0, ``cpu.max``) where the host has it, else v1 (the ``memory`` hierarchy's
``memory.limit_in_bytes``, and ``memory.memsw.limit_in_bytes`` where swap is accounted; the ``cpu``
hierarchy's CFS quota; ``cpuacct`` for the CPU time). The groups are ``swarmmap-<run id>/robot-<i>``,
made by ``up`` (root, or a user to whom the subtree is delegated) and removed when the run is over
(after a ``kill -9`` of ``up``, by a guard process that waits for it to die: ``python -m
swarmmap.services.up.budget PID GROUP...``);
where none can be made, the run is refused before anything starts, saying why. A service joins its
robot's group before it runs (``preexec_fn``), so none of its memory is ever outside it. At the end,
each robot's peak memory and CPU time against its budget go to the log and to ``summary.json``
(``budget``)."""

from __future__ import annotations

import logging
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

from swarmmap.shared.run.config import ConfigError
from swarmmap.shared.run.sections import Budget

log = logging.getLogger("up")
ROOT = Path("/sys/fs/cgroup")
PERIOD_US = 100_000  # the CFS period a CPU quota is a share of


class Cgroups:
    """The run's group per robot (see the module); :meth:`joiner` is the ``preexec_fn`` that puts a
    process in robot ``i``'s, :meth:`usage` what each robot used."""

    def __init__(self, run_id: str, robots: int, budget: Budget, root: Path = ROOT):
        self.budget, self.root = budget, root
        name = f"swarmmap-{run_id}"
        self.v2 = (root / "cgroup.controllers").exists() and {"memory", "cpu"} <= set(
            (root / "cgroup.controllers").read_text().split())
        try:
            if self.v2:
                self.tops = [root / name]
                (root / "cgroup.subtree_control").write_text("+memory +cpu")
                self.tops[0].mkdir(exist_ok=True)
                (self.tops[0] / "cgroup.subtree_control").write_text("+memory +cpu")
            else:
                if not (root / "memory" / "memory.limit_in_bytes").exists() or not (root / "cpu" / "cpu.cfs_quota_us").exists():
                    raise OSError(f"{root} has neither cgroup v2 with the memory and cpu controllers nor v1's memory and "
                                  "cpu hierarchies")
                acct = root / "cpuacct" if (root / "cpuacct" / "cpuacct.usage").exists() else root / "cpu"
                self.tops = [root / "memory" / name, root / "cpu" / name] + ([acct / name] if acct != root / "cpu" else [])
                for top in self.tops:
                    top.mkdir(exist_ok=True)
            self.groups = [[top / f"robot-{i}" for top in self.tops] for i in range(robots)]
            for i in range(robots):
                self.make(i)
        except OSError as exc:
            raise ConfigError(f"config error:\n  up.budget: no control group for the robots' budget could be made "
                              f"({exc}); run up as root, or on a host whose cgroup subtree is delegated to this user, or "
                              "drop --budget") from None

    def make(self, i: int) -> None:
        b = self.budget
        for group in self.groups[i]:
            group.mkdir(exist_ok=True)
        if self.v2:
            group = self.groups[i][0]
            (group / "memory.max").write_text(str(b.memory_bytes))
            if (group / "memory.swap.max").exists():
                (group / "memory.swap.max").write_text("0")
            (group / "cpu.max").write_text(f"{int(b.cpus * PERIOD_US)} {PERIOD_US}")
            return
        memory, cpu = self.groups[i][0], self.groups[i][1]
        (memory / "memory.limit_in_bytes").write_text(str(b.memory_bytes))
        if (memory / "memory.memsw.limit_in_bytes").exists():  # (no swap beyond the memory)
            (memory / "memory.memsw.limit_in_bytes").write_text(str(b.memory_bytes))
        (cpu / "cpu.cfs_period_us").write_text(str(PERIOD_US))
        (cpu / "cpu.cfs_quota_us").write_text(str(int(b.cpus * PERIOD_US)))

    def joiner(self, robot: int):
        """A function (run in the child before it runs the service) that moves it into robot ``robot``'s group."""
        files = [group / ("cgroup.procs" if self.v2 else "tasks") for group in self.groups[robot]]

        def join() -> None:
            for f in files:
                with open(f, "w") as out:
                    out.write(str(os.getpid()))

        return join

    def usage(self) -> dict[int, dict[str, float]]:
        """Each robot's peak memory (bytes) and CPU time (s) so far."""
        out = {}
        for i, groups in enumerate(self.groups):
            try:
                if self.v2:
                    g = groups[0]
                    peak = int((g / "memory.peak").read_text()) if (g / "memory.peak").exists() else 0
                    usec = next(int(line.split()[1]) for line in (g / "cpu.stat").read_text().splitlines()
                                if line.startswith("usage_usec"))
                    cpu_s = usec / 1e6
                else:
                    peak = int((groups[0] / "memory.max_usage_in_bytes").read_text())
                    acct = groups[2] if len(groups) > 2 else groups[1]
                    cpu_s = int((acct / "cpuacct.usage").read_text()) / 1e9
                oom = self.oom_kills(i)
            except (OSError, ValueError, StopIteration):
                continue
            out[i] = {"peak_memory_bytes": peak, "cpu_s": round(cpu_s, 3), "oom_kills": oom}
        return out

    def oom_kills(self, i: int) -> int:
        g = self.groups[i][0]
        events = g / ("memory.events" if self.v2 else "memory.oom_control")
        for line in events.read_text().splitlines():
            key, _, value = line.partition(" ")
            if key == "oom_kill":
                return int(value)
        return 0

    def report(self, wall_s: float) -> dict:
        """``summary.json``'s ``budget`` section, each robot's line logged."""
        b, used = self.budget, self.usage()
        robots = {}
        for i, u in sorted(used.items()):
            share = u["cpu_s"] / wall_s if wall_s > 0 else 0.0
            robots[str(i)] = {**u, "peak_share": round(u["peak_memory_bytes"] / b.memory_bytes, 4),
                              "cpus_used": round(share, 3)}
            log.info("robot %d's budget: peak memory %.0f MiB of %.0f MiB (%.0f%%), CPU %.1f s in %.0f s (%.2f of %g CPU)%s",
                     i, u["peak_memory_bytes"] / 1024**2, b.memory_bytes / 1024**2,
                     100 * u["peak_memory_bytes"] / b.memory_bytes, u["cpu_s"], wall_s, share, b.cpus,
                     f"; {u['oom_kills']} process(es) killed at the memory limit" if u["oom_kills"] else "")
        return {"memory_bytes": b.memory_bytes, "cpus": b.cpus, "cgroup": "v2" if self.v2 else "v1", "robots": robots}

    def close(self) -> None:
        """Remove the groups (their processes are gone)."""
        for groups in self.groups:
            for g in groups:
                try:
                    g.rmdir()
                except OSError:
                    pass
        for top in self.tops:
            try:
                top.rmdir()
            except OSError:
                pass


def start_guard(groups: Cgroups, log_path: Path) -> subprocess.Popen:
    """Start the process that removes the run's groups once this process has died, however it died."""
    dirs = [str(g) for robot in groups.groups for g in robot] + [str(top) for top in groups.tops]
    with log_path.open("a") as out:
        return subprocess.Popen([sys.executable, "-m", "swarmmap.services.up.budget", str(os.getpid()), *dirs],
                                stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)


def guard(pid: int, dirs: list[Path], wait_s: float = 60.0, grace_s: float = 10.0) -> int:
    """Wait until process ``pid`` has ended, then remove ``dirs`` (groups, then their parents) as
    soon as their processes are gone: each service dies with ``up``, and one still in a group
    ``grace_s`` later (one that was being started as ``up`` died) is killed; for up to ``wait_s``."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        fd = None
    if fd is not None:
        select.select([fd], [], [])
        os.close(fd)
    deadline = time.monotonic() + wait_s
    left = [d for d in dirs if d.exists()]
    removed = []
    while left and time.monotonic() < deadline:
        for d in list(left):
            try:
                d.rmdir()
                removed.append(d)
                left.remove(d)
            except FileNotFoundError:
                left.remove(d)
            except OSError:
                pass  # (processes still in it, or its groups)
        if left and time.monotonic() > deadline - wait_s + grace_s:
            for d in left:
                for stray in (d / "cgroup.procs").read_text().split() if (d / "cgroup.procs").exists() else []:
                    try:
                        os.kill(int(stray), signal.SIGKILL)
                        log.warning("killed process %s, left in %s after up died", stray, d)
                    except (ProcessLookupError, ValueError):
                        pass
        if left:
            time.sleep(0.5)
    if removed:
        log.warning("up (pid %d) ended without removing its control groups: removed %s", pid, ", ".join(map(str, removed)))
    if left:
        log.error("control groups still in use after %.0f s, left: %s", wait_s, ", ".join(map(str, left)))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level="INFO", format="%(asctime)s %(levelname)s budget-guard: %(message)s")
    sys.exit(guard(int(sys.argv[1]), [Path(a) for a in sys.argv[2:]]))
