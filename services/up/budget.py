"""A robot's budget (``up.budget``, ``swarmmap up --budget MEMORY,CPUS``): every robot's services
(its lidar streamer and learner, and its router under ``--netns``) run in a Linux control group of
their own that holds them to ``MEMORY`` (bytes with K, M or G: powers of 1024) and ``CPUS`` (cores,
fractions allowed), the same for every robot or one each (``"512M,0.5;1G,1"``).

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

import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.limits import read_group_file
from swarmmap.shared.run.runtime import wait_for_exit
from swarmmap.shared.run.sections import Budget

log = logging.getLogger("up")
ROOT = Path("/sys/fs/cgroup")
PERIOD_US = 100_000  # the CFS period a CPU quota is a share of
MiB = 1024**2
# What a robot's services need beside what the probe measures of its learner, measured on this
# project's services (x86-64, CPU torch, a demo run under up --budget): a lidar streamer's anonymous
# and shared memory (51 and 17 MB); a router's; what a learner holds beyond the probe (its Zenoh
# session and buffers, the world's map and its validation set: 39 MB); the pages of the libraries a
# robot's processes keep using (torch's, Zenoh's, numpy's: a demo robot ran in 384 MiB and was
# killed in 352 MiB, with 325 MiB of anonymous and shared memory).
LIDAR_BYTES = 80 * MiB
ROUTER_BYTES = 192 * MiB
LEARNER_SESSION_BYTES = 40 * MiB
FILES_BYTES = 64 * MiB
STEP = 32 * MiB  # a budget named in a refusal is rounded up to this
AGAIN = 1.05  # the probe measured again (a learner's memory varies by a few MiB from run to run): within this


def needs(cfg: RunConfig, path_lengths_m: list[float], expected_scans: int, size_m: tuple[float, float],
          router: bool) -> dict[str, int]:
    """What one robot's services need in memory (bytes, each service and ``total``), for the robot
    with the most data: its learner's working memory measured by a probe process
    (:mod:`swarmmap.services.learner.probe`), the rest from :data:`LIDAR_BYTES` and its peers."""
    w, s, robots = cfg.world, cfg.learner, cfg.robots
    scans = max([int(v / w.speed_mps * w.lidar_rate_hz) + 1 for v in path_lengths_m] or [-(-expected_scans // robots)])
    if cfg.explore.active:  # an exploring robot keeps the scans of every leg it drove, up to its distance budget
        scans = int(cfg.explore.distance_m / w.speed_mps * w.lidar_rate_hz) + 1
    elif s.data == "online":  # (the sliding window)
        scans = min(scans, s.window_scans)
    points = scans * w.lidar_beams * (cfg.lidar.samples_per_beam + 1)
    res = s.map_resolution_m or w.grid_resolution_m
    cells = math.ceil(size_m[0] / res) * math.ceil(size_m[1] / res)
    degree = min(2, robots - 1) if s.graph == "ring" else robots - 1
    val = w.val_scans * w.val_beams * (cfg.lidar.samples_per_beam + 1)
    doc = {"config": cfg.model_dump(mode="json"), "points": points, "cells": cells, "size_m": list(size_m), "degree": degree,
           "val_points": val}
    said = ""
    try:
        done = subprocess.run([sys.executable, "-m", "swarmmap.services.learner.probe"], input=json.dumps(doc), text=True,
                              capture_output=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
        said = done.stderr.strip()[-400:]
        probe = json.loads(done.stdout.strip().splitlines()[-1])
    except (subprocess.TimeoutExpired, ValueError, IndexError) as exc:
        raise ConfigError(f"config error:\n  up.budget: the learner's memory could not be measured ({exc}): {said}") from None
    # Beside the probe: the collector's and the learner's own copies of the points (x, y, label as
    # float32), the neighbours' States a round holds (received, and the screen's references).
    learner = probe["peak_anon_bytes"] + 2 * points * 12 + 2 * degree * probe["state_bytes"] + LEARNER_SESSION_BYTES
    out = {"learner": learner, "lidar": LIDAR_BYTES, **({"router": ROUTER_BYTES} if router else {}), "libraries": FILES_BYTES}
    return {**out, "total": sum(out.values()), "points": points, "cells": cells}


def checked_budgets(cfg: RunConfig, path_lengths_m: list[float], expected_scans: int, size_m: tuple[float, float],
                    router: bool) -> list[Budget]:
    """Each robot's budget (``up.budget``; none: empty), once what a robot's services need has been
    measured (:func:`needs`): a ConfigError naming the smallest budget that fits where one is short."""
    if not cfg.up.budget:
        return []
    budgets = [b for i in range(cfg.robots) if (b := cfg.budget(i)) is not None]
    need = needs(cfg, path_lengths_m, expected_scans, size_m, router)
    log.info("each robot's services need about %.0f MiB (learner %.0f MiB, measured on %s training points)",
             need["total"] / MiB, need["learner"] / MiB, f"{need['points']:,}")
    refuse_if_short(budgets, need)
    return budgets


def smallest(total: int) -> int:
    """The smallest budget (bytes, a multiple of :data:`STEP`) that holds ``total`` and what a
    measurement of it again may find (a few MiB more or less: :data:`AGAIN`)."""
    return -(-int(total * AGAIN) // STEP) * STEP


def refuse_if_short(budgets: list[Budget], need: dict[str, int]) -> None:
    """A ConfigError naming each robot whose budget cannot hold ``need`` and the smallest that would."""
    short = [i for i, b in enumerate(budgets) if b.memory_bytes < need["total"]]
    if not short:
        return
    parts = ", ".join(f"{k} {v / MiB:.0f} MiB" for k, v in need.items() if k not in ("total", "points", "cells"))
    least = smallest(need["total"])
    robots = "every robot's" if len(short) == len(budgets) else "robot " + ", ".join(map(str, short)) + "'s"
    cpus = budgets[short[0]].cpus
    raise ConfigError(f"config error:\n  up.budget: {robots} budget ({budgets[short[0]]}) cannot hold its services: "
                      f"they need about {need['total'] / MiB:.0f} MiB ({parts}; its learner holds {need['points']:,} "
                      f"training points and maps {need['cells']:,} cells). The smallest budget that fits: "
                      f"--budget {least // MiB}M,{cpus:g}; or a smaller model (learner.model_shape) or fewer points "
                      "(learner.samples_per_beam)")


class Cgroups:
    """The run's group per robot (see the module); :meth:`joiner` is the ``preexec_fn`` that puts a
    process in robot ``i``'s, :meth:`usage` what each robot used."""

    def __init__(self, run_id: str, budgets: list[Budget], root: Path = ROOT):
        self.budgets, self.root = budgets, root
        robots = len(budgets)
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
        b = self.budgets[i]
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
                    now = int((g / "memory.current").read_text()) if (g / "memory.current").exists() else 0
                    usec = next(int(line.split()[1]) for line in (g / "cpu.stat").read_text().splitlines()
                                if line.startswith("usage_usec"))
                    cpu_s = usec / 1e6
                else:
                    peak = int((groups[0] / "memory.max_usage_in_bytes").read_text())
                    now = int(read_group_file(groups[0] / "memory.usage_in_bytes") or 0)
                    acct = groups[2] if len(groups) > 2 else groups[1]
                    cpu_s = int((acct / "cpuacct.usage").read_text()) / 1e9
                oom, hits = self.oom_kills(i), self.limit_hits(i)
            except (OSError, ValueError, StopIteration):
                continue
            out[i] = {"peak_memory_bytes": peak, "memory_bytes_now": now, "cpu_s": round(cpu_s, 3), "oom_kills": oom,
                      "limit_hits": hits}
        return out

    def oom_kills(self, i: int) -> int:
        g = self.groups[i][0]
        events = g / ("memory.events" if self.v2 else "memory.oom_control")
        for line in events.read_text().splitlines():
            key, _, value = line.partition(" ")
            if key == "oom_kill":
                return int(value)
        return 0

    def limit_hits(self, i: int) -> int:
        """How often robot ``i``'s memory reached its limit (the kernel then reclaims its pages, and
        a group that keeps hitting it spends its time reading them back)."""
        g = self.groups[i][0]
        if not self.v2:
            return int(read_group_file(g / "memory.failcnt") or 0)
        for line in (read_group_file(g / "memory.events") or "").splitlines():
            key, _, value = line.partition(" ")
            if key == "max":
                return int(value)
        return 0

    def live(self, wall_s: float) -> dict:
        """What ``swarmmap status`` shows of the budget while the run lasts (``RUN_DIR/budget.json``)."""
        return {"wall_s": round(wall_s, 1), "robots": {str(i): {**u, "memory_limit_bytes": self.budgets[i].memory_bytes,
                                                                "cpus": self.budgets[i].cpus}
                                                       for i, u in self.usage().items()}}

    def report(self, wall_s: float) -> dict:
        """``summary.json``'s ``budget`` section, each robot's line logged."""
        used, robots = self.usage(), {}
        for i, u in sorted(used.items()):
            b = self.budgets[i]
            share = u["cpu_s"] / wall_s if wall_s > 0 else 0.0
            robots[str(i)] = {**u, "memory_bytes": b.memory_bytes, "cpus": b.cpus,
                              "peak_share": round(u["peak_memory_bytes"] / b.memory_bytes, 4),
                              "cpus_used": round(share, 3)}
            log.info("robot %d's budget: peak memory %.0f MiB of %.0f MiB (%.0f%%), CPU %.1f s in %.0f s (%.2f of %g CPU)%s%s",
                     i, u["peak_memory_bytes"] / 1024**2, b.memory_bytes / 1024**2,
                     100 * u["peak_memory_bytes"] / b.memory_bytes, u["cpu_s"], wall_s, share, b.cpus,
                     f"; {u['oom_kills']} process(es) killed at the memory limit" if u["oom_kills"] else "",
                     f"; at its memory limit {u['limit_hits']} time(s) (pages reclaimed)" if u["limit_hits"] else "")
        same = len(set(self.budgets)) == 1
        return {"memory_bytes": self.budgets[0].memory_bytes if same else None, "cpus": self.budgets[0].cpus if same else None,
                "cgroup": "v2" if self.v2 else "v1", "robots": robots}

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
    wait_for_exit(pid)
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
