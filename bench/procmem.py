"""Memory of a process tree, sampled from /proc (Linux), for the benches.

Per process: its resident set (RSS, what one process holds, shared libraries included). For
the whole tree: the sum of the proportional set sizes (PSS: each shared page divided among the
processes that map it), the memory the run really takes; a sum of RSS would count torch's
libraries and Zenoh's shared-memory segments once per process."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from pathlib import Path


def children(pid: int) -> set[int]:
    """Every live descendant of ``pid``."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            kids = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            continue
        for k in map(int, kids):
            if k not in out:
                out.add(k)
                todo.append(k)
    return out


def command(pid: int) -> str:
    """The command line of ``pid`` ('' when it is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def rss_kib(pid: int) -> tuple[int, int]:
    """(RSS KiB now, peak RSS KiB so far: the kernel's high-water mark) of ``pid``; (0, 0) when
    it is gone. Cheap: /proc/<pid>/status walks no page tables."""
    fields = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            name, _, rest = line.partition(":")
            if name in ("VmRSS", "VmHWM"):
                fields[name] = int(rest.split()[0])
    except (OSError, ValueError, IndexError):
        return 0, 0
    return fields.get("VmRSS", 0), fields.get("VmHWM", 0)


def pss_kib(pid: int) -> int:
    """Proportional set size of ``pid`` in KiB (0 when it is gone). Costly: the kernel walks
    the process's page tables (about 5 ms for a learner holding torch), so it is sampled rarely."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            name, _, rest = line.partition(":")
            if name == "Pss":
                return int(rest.split()[0])
    except (OSError, ValueError, IndexError):
        pass
    return 0


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds ``pid`` has used so far (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def service_of(cmd: str) -> str:
    """The swarmmap service a command line runs (``cli learner ...``), or ``other``."""
    words = cmd.split()
    if "swarmmap.services.cli" in words:
        at = words.index("swarmmap.services.cli")
        if at + 1 < len(words):
            return words[at + 1]
    return "other"


class MemorySampler(threading.Thread):
    """Peak RSS of each learner process and peak PSS of the whole process tree of a run.

    Every ``every`` s it reads each process's CPU time and RSS (cheap); every ``pss_every`` s
    the whole tree's PSS (a page-table walk per process: 0.3 s of CPU for the 67 processes of a
    32-robot run, which sampled every 0.25 s took a sizeable share of a 2-core machine from the
    run it measured, more the larger the team). ``own_cpu_s`` is the CPU the sampler itself
    used, for the benches to print."""

    def __init__(self, root: int, every: float = 0.25, pss_every: float = 5.0):
        super().__init__(daemon=True)
        self.root, self.every, self.pss_every = root, every, pss_every
        self.learner_peak: dict[int, int] = {}  # pid -> KiB, the kernel's high-water mark
        self.total_peak = 0  # KiB, PSS of every process of the run
        self.learner_series: list[tuple[float, int]] = []  # (seconds, KiB of every learner together)
        self.cpu: dict[int, tuple[str, float]] = {}  # pid -> (service, CPU seconds at its last sample)
        self.own_cpu_s = 0.0
        self.commands: dict[int, str] = {}  # pid -> its command line
        self.stop = threading.Event()

    def run(self) -> None:
        t0 = time.monotonic()
        cpu0 = time.thread_time()
        commands = self.commands
        root_cmd = command(self.root)
        next_pss = t0
        while not self.stop.is_set():
            learners = 0
            pids = children(self.root) | {self.root}
            for pid in pids:
                cmd = commands.get(pid) or command(pid)
                if not cmd:
                    continue
                if pid == self.root or cmd != root_cmd:  # a child forked but not yet exec'd shows the launcher's
                    commands[pid] = cmd
                # CPU time only grows; a process that exits between the listing and this read gives 0
                self.cpu[pid] = (service_of(cmd), max(cpu_seconds(pid), self.cpu.get(pid, ("", 0.0))[1]))
                if " learner " in cmd:
                    now, peak = rss_kib(pid)
                    self.learner_peak[pid] = max(self.learner_peak.get(pid, 0), peak)
                    learners += now
            if time.monotonic() >= next_pss:
                self.total_peak = max(self.total_peak, sum(pss_kib(pid) for pid in pids))
                next_pss = time.monotonic() + self.pss_every
            if learners:
                self.learner_series.append((time.monotonic() - t0, learners))
            self.own_cpu_s = time.thread_time() - cpu0
            self.stop.wait(self.every)

    def cpu_by_service(self) -> dict[str, float]:
        """CPU seconds each kind of service used (as last sampled), summed over its processes."""
        out: dict[str, float] = {}
        for service, seconds in self.cpu.values():
            out[service] = out.get(service, 0.0) + seconds
        return out


def growth(series: list[tuple[float, int]]) -> float:
    """KiB the learners grew from the middle of their life to its end (the mean of the last
    tenth of the samples against that of the tenth at the middle)."""
    if len(series) < 20:
        return 0.0
    n = len(series)
    tenth = max(1, n // 10)
    mid = [k for _, k in series[n // 2 - tenth // 2 : n // 2 + tenth // 2 + 1]]
    end = [k for _, k in series[-tenth:]]
    return sum(end) / len(end) - sum(mid) / len(mid)


def run_sampled(cmd: list[str], env: dict[str, str] | None = None) -> tuple[int, str, float, MemorySampler]:
    """Run ``cmd`` while sampling its process tree's memory: exit status, stderr, seconds, sampler."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    sampler = MemorySampler(proc.pid)
    sampler.start()
    _, err = proc.communicate()
    sampler.stop.set()
    sampler.join()
    return proc.returncode, err, time.perf_counter() - t0, sampler
