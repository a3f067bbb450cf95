"""A learner that fits its robot's budget: it reads the budget (``up.budget`` for its robot, and the
limits of the control group it runs in: ``up``'s, a container's, a SLURM step's; the smaller of
each: :func:`~swarmmap.shared.run.limits.robot_budget`), then trades what costs no accuracy and
says so in its log:

- torch threads: no more than the CPUs of its budget (at least one): more threads than the CFS
  quota allows only wait on each other;
- Zenoh shared memory off, where ``zenoh.shared_memory`` is unset: its segments (about 80 MiB a
  process) count against the budget, and a robot's States leave the robot anyway;
- memory blocks of 4 MiB and more (a validation pass's activations) returned to the system when
  freed (glibc's ``mallopt``): else the allocator keeps the largest freed block's size, and a
  quickstart learner held 424 MiB where it needs 280 (its rounds took no longer).

What would cost accuracy (a smaller network, fewer points) is not traded silently: ``up --budget``
refuses at start a run whose learner cannot fit, naming the smallest budget that would
(:func:`swarmmap.services.up.budget.needs`)."""

from __future__ import annotations

import math

from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.run.limits import (
    BIG_BLOCK,
    SHARED_MEMORY_OFF,
    Limits,
    return_big_blocks,
    robot_budget,
    without_shared_memory,
)


def fit(cfg: RunConfig, robot: int, limits: Limits | None = None) -> tuple[RunConfig, Limits, list[str]]:
    """``cfg`` fitted to robot ``robot``'s budget (:func:`robot_budget` of ``limits``), the budget
    it fitted to, and what it traded (none: unchanged)."""
    budget = robot_budget(cfg, robot, limits)
    if budget.memory_bytes is None and budget.cpus is None:
        return cfg, budget, []
    cfg, off = without_shared_memory(cfg, budget)
    cfg = cfg.model_copy(deep=True)
    traded = []
    if budget.cpus is not None and cfg.learner.torch_threads > (threads := max(1, math.floor(budget.cpus))):
        traded.append(f"torch threads {cfg.learner.torch_threads} -> {threads}")
        cfg.learner.torch_threads = threads
    if off:
        traded.append(SHARED_MEMORY_OFF)
    if budget.memory_bytes is not None and return_big_blocks():
        traded.append(f"freed blocks of {BIG_BLOCK >> 20} MiB and more returned to the system at once")
    return cfg, budget, traded
