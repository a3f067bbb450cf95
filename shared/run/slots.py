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
When every slot is taken, the waiters queue on one more lock file (asleep in the kernel) and
only the one at the head of the line waits for a free slot: a lock cannot be waited for as
"any of N", and waiting on one given slot left the other core idle while its own queue was
empty (measured: DiNNO's 7 robots on 2 cores took 11% longer so). A holder that lets go of
its slot writes a byte to a FIFO that the head of the line sleeps on (woken at once); the head
also looks every ``RECHECK_S``, for a holder killed before it could write. Polling instead
(every 0.5 ms) cost 15-20% of a round of the tiny model at 16 and 32 learners.
"""

from __future__ import annotations

import fcntl
import os
import select
import stat
import tempfile
import time
from pathlib import Path

RECHECK_S = 0.02  # the head of the line looks for a free slot at least this often


def slots_dir(run_id: str) -> Path:
    """The run's slot directory on this host: per user and run, never shared between hosts."""
    return Path(tempfile.gettempdir()) / f"swarmmap-{os.getuid()}-compute-{run_id}"


def own_directory(directory: Path) -> None:
    """Refuse a slot directory that another user made or may write to (a shared ``/tmp``: a
    stranger's directory there could hold the slots, or plant links)."""
    st = os.lstat(directory)
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise OSError(f"{directory} is not a directory of this user's alone (owner {st.st_uid}, mode "
                      f"{stat.filemode(st.st_mode)})")


class ComputeSlots:
    """``with slots:`` holds one of ``n`` host-wide slots (tried from ``home`` on, spreading the team over them)."""

    def __init__(self, directory: Path, n: int, home: int = 0):
        if n < 1:
            raise ValueError(f"compute slots must be at least 1, got {n}")
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        own_directory(directory)
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW
        self.fds = [os.open(directory / f"slot-{i}", flags, 0o600) for i in range(n)]
        self.line = os.open(directory / "line", flags, 0o600)
        try:
            os.mkfifo(directory / "freed", 0o600)
        except FileExistsError:
            pass
        self.freed = os.open(directory / "freed", os.O_RDWR | os.O_NONBLOCK | os.O_NOFOLLOW)  # (read-write: no end of file)
        if not stat.S_ISFIFO(os.fstat(self.freed).st_mode):
            self.close()
            raise OSError(f"{directory / 'freed'} is not a FIFO")
        self.home = home % n
        self.held: int | None = None
        self.wait_s = 0.0  # time spent waiting for a slot, over all rounds

    def try_take(self) -> bool:
        """Take a free slot, from this process's own on; False when all are taken."""
        n = len(self.fds)
        for i in range(n):
            fd = self.fds[(self.home + i) % n]
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            self.held = fd
            return True
        return False

    def __enter__(self) -> ComputeSlots:
        if self.try_take():
            return self
        t0 = time.perf_counter()
        fcntl.flock(self.line, fcntl.LOCK_EX)  # in line, asleep; the head of the line waits for a slot to free
        try:
            while True:
                self.drain()  # (before looking: a slot freed after the look wakes the select)
                if self.try_take():
                    break
                select.select([self.freed], [], [], RECHECK_S)
        finally:
            fcntl.flock(self.line, fcntl.LOCK_UN)
        self.wait_s += time.perf_counter() - t0
        return self

    def __exit__(self, *exc: object) -> None:
        if self.held is not None:
            fcntl.flock(self.held, fcntl.LOCK_UN)
            self.held = None
            try:
                os.write(self.freed, b"1")  # wake the head of the line, if any
            except BlockingIOError:
                pass  # (the FIFO is full of wake-ups nobody needed: the head drains them)

    def drain(self) -> None:
        """Drop the wake-ups written so far."""
        try:
            while os.read(self.freed, 4096):
                pass
        except BlockingIOError:
            pass

    def close(self) -> None:
        """Let go of the files (and so of a slot still held); a second call does nothing."""
        for fd in [*self.fds, self.line, self.freed]:
            if fd is not None:
                os.close(fd)
        self.fds, self.line, self.freed, self.held = [], None, None, None
