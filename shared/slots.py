"""Compute slots: at most N processes of one host train at a time (``learner.compute_slots``).

More learner processes than cores on one host (32 robots on a laptop) all runnable at once
make the kernel slice their training steps into each other: every step runs on a cold cache
and is preempted a few times, and a round costs more CPU than the same work done one learner
after another. With N slots (N = the host's cores), a learner takes a slot for its round's
training and hands it on when it sends its State, so at most N train at once, each on a core
of its own until its round's steps are done; the others wait in the kernel, not spinning.

A slot is an exclusive ``flock`` on one of N files in a directory of this host's temporary
directory (per user and run): the kernel releases it when its holder exits or is killed, so
a crashed learner never keeps a slot. Containers with their own ``/tmp`` do not share slots.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
import time
from pathlib import Path


def slots_dir(run_id: str) -> Path:
    """The run's slot directory on this host: per user and run, never shared between hosts."""
    return Path(tempfile.gettempdir()) / f"swarmmap-{os.getuid()}-compute-{run_id}"


class ComputeSlots:
    """``with slots:`` holds one of ``n`` host-wide slots; ``home`` spreads waiters over them."""

    def __init__(self, directory: Path, n: int, home: int = 0):
        if n < 1:
            raise ValueError(f"compute slots must be at least 1, got {n}")
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.fds = [os.open(directory / f"slot-{i}", os.O_RDWR | os.O_CREAT, 0o600) for i in range(n)]
        self.home = home % n
        self.held: int | None = None
        self.wait_s = 0.0  # time spent waiting for a slot, over all rounds

    def __enter__(self) -> ComputeSlots:
        n = len(self.fds)
        for i in range(n):  # a free slot first, from this learner's own on
            fd = self.fds[(self.home + i) % n]
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            self.held = fd
            return self
        t0 = time.perf_counter()
        fd = self.fds[self.home]
        fcntl.flock(fd, fcntl.LOCK_EX)  # all busy: queue on its own one (released within a holder's round)
        self.wait_s += time.perf_counter() - t0
        self.held = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self.held is not None:
            fcntl.flock(self.held, fcntl.LOCK_UN)
            self.held = None

    def close(self) -> None:
        for fd in self.fds:
            os.close(fd)
        self.fds = []
