"""A process's budget: the memory and CPU limits of the control groups it runs in (``up``'s, a
container's, a SLURM step's: :func:`own_limits`) and its robot's stated budget (``up.budget``),
the tighter of each (:func:`robot_budget`); and the allocator told to return large freed blocks at
once (:func:`return_big_blocks`). What a learner trades for its budget: services/learner/fitting.py."""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from pathlib import Path

from swarmmap.shared.run.config import RunConfig

UNLIMITED = 1 << 60  # v1's "no limit" is a page-rounded 2**63 - 1
BIG_BLOCK = 4 * 1024**2
M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter


def return_big_blocks(threshold: int = BIG_BLOCK) -> bool:
    """Have this process's allocator map blocks of ``threshold`` bytes and more apart and unmap
    them when freed (a fixed threshold: glibc otherwise raises it to the largest block freed);
    False where the C library has no ``mallopt`` (not glibc)."""
    try:
        return ctypes.CDLL("libc.so.6").mallopt(M_MMAP_THRESHOLD, threshold) == 1
    except (OSError, AttributeError):
        return False


@dataclass(frozen=True)
class Limits:
    """A process's memory (bytes) and CPUs, None where nothing limits them."""

    memory_bytes: int | None = None
    cpus: float | None = None

    def __str__(self) -> str:
        mem = "no memory limit" if self.memory_bytes is None else f"{self.memory_bytes / 1024**2:.0f} MiB"
        cpu = "no CPU limit" if self.cpus is None else f"{self.cpus:g} CPU"
        return f"{mem}, {cpu}"


def read_group_file(path: Path) -> str | None:
    """A control group's file, stripped; None where it cannot be read (no such file, a group gone)."""
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _smaller(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else min(a, b)


def own_limits(proc: Path = Path("/proc/self/cgroup"), root: Path = Path("/sys/fs/cgroup")) -> Limits:
    """The memory and CPU limits of the control group this process is in and of its ancestors
    (cgroup v2 ``memory.max``/``cpu.max``, or v1 ``memory.limit_in_bytes``/``cpu.cfs_quota_us``).
    In a container, whose own group is mounted at the root, the root's files are its limits."""
    memory: float | None = None
    cpus: float | None = None
    for line in (read_group_file(proc) or "").splitlines():
        _, controllers, path = line.split(":", 2)
        v2 = controllers == ""
        names = set(controllers.split(","))
        if not v2 and not names & {"memory", "cpu"}:
            continue
        hierarchy = root if v2 else root / ("memory" if "memory" in names else ",".join(sorted(names)))
        if not v2 and not hierarchy.exists():
            hierarchy = root / ("memory" if "memory" in names else "cpu")
        parts = [p for p in path.split("/") if p]
        for depth in range(len(parts), -1, -1):
            group = hierarchy.joinpath(*parts[:depth])
            if not group.exists():
                continue
            if v2 or "memory" in names:
                raw = read_group_file(group / ("memory.max" if v2 else "memory.limit_in_bytes"))
                if raw and raw != "max" and int(raw) < UNLIMITED:
                    memory = _smaller(memory, int(raw))
            if v2 or "cpu" in names:
                if v2:
                    raw = read_group_file(group / "cpu.max")
                    quota, _, period = (raw or "max").partition(" ")
                else:
                    quota, period = read_group_file(group / "cpu.cfs_quota_us") or "-1", read_group_file(group / "cpu.cfs_period_us") or ""
                if quota not in ("max", "-1") and period:
                    cpus = _smaller(cpus, int(quota) / int(period))
    return Limits(int(memory) if memory is not None else None, cpus)


def robot_budget(cfg: RunConfig, robot: int, limits: Limits | None = None) -> Limits:
    """Robot ``robot``'s budget: the tighter of its ``up.budget`` and ``limits`` (default: this
    process's :func:`own_limits`), each of memory and CPUs."""
    stated = cfg.budget(robot)
    own = own_limits() if limits is None else limits
    return Limits(_smaller(stated.memory_bytes if stated else None, own.memory_bytes),
                  _smaller(stated.cpus if stated else None, own.cpus))


SHARED_MEMORY_OFF = "Zenoh shared memory off (zenoh.shared_memory: true keeps it)"


def without_shared_memory(cfg: RunConfig, budget: Limits) -> tuple[RunConfig, bool]:
    """``cfg`` with Zenoh's shared memory off where a memory budget holds the process and
    ``zenoh.shared_memory`` is unset (its segments, about 80 MiB a process, would count against the
    budget), a copy; and whether it was turned off."""
    if budget.memory_bytes is None or cfg.zenoh.shared_memory is not None:
        return cfg, False
    cfg = cfg.model_copy(deep=True)
    cfg.zenoh.shared_memory = False
    return cfg, True
