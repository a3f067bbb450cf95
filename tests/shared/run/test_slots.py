"""Compute slots between real processes: never more holders than slots, none lost to a crash."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from swarmmap.shared.run.slots import ComputeSlots

HOLD = """
import sys, time
from pathlib import Path
from swarmmap.shared.run.slots import ComputeSlots
slots = ComputeSlots(Path(sys.argv[1]), int(sys.argv[2]), home=int(sys.argv[3]))
for _ in range(int(sys.argv[4])):
    with slots:
        t0 = time.monotonic()
        print("in", flush=True)
        time.sleep(float(sys.argv[5]))
        print(f"{t0} {time.monotonic()}", flush=True)
"""


def holders(directory, n, home, rounds, hold_s) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", HOLD, str(directory), str(n), str(home), str(rounds), str(hold_s)],
                            stdout=subprocess.PIPE, text=True)


@pytest.mark.integration
def test_no_more_processes_hold_a_slot_than_there_are_slots(tmp_path):
    """Six processes, two slots, each taking one three times: at no instant more than two inside,
    and every process gets all its turns (waiters are not starved)."""
    procs = [holders(tmp_path, 2, i, 3, 0.15) for i in range(6)]
    spans = []
    for p in procs:
        out, _ = p.communicate(timeout=60)
        assert p.returncode == 0
        mine = [tuple(map(float, line.split())) for line in out.splitlines() if line != "in"]
        assert len(mine) == 3, f"a process got {len(mine)} of its 3 turns"
        spans += mine
    events = sorted([(t0, 1) for t0, _ in spans] + [(t1, -1) for _, t1 in spans], key=lambda e: (e[0], e[1]))
    inside = most = 0
    for _, d in events:
        inside += d
        most = max(most, inside)
    assert most == 2, f"{most} processes held a slot at once (2 slots)"


@pytest.mark.integration
def test_a_killed_holder_frees_its_slot(tmp_path):
    """A learner killed while training never keeps its slot: the kernel drops its lock."""
    holder = holders(tmp_path, 1, 0, 1, 600)
    try:
        assert holder.stdout.readline().strip() == "in"
        waiter = holders(tmp_path, 1, 0, 1, 0.01)
        time.sleep(0.5)
        assert waiter.poll() is None, "a second process took the only slot while it was held"
        holder.send_signal(signal.SIGKILL)
        out, _ = waiter.communicate(timeout=30)
        assert waiter.returncode == 0 and "in" in out
    finally:
        holder.kill()
        holder.wait()


def test_slots_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="at least 1"):
        ComputeSlots(tmp_path, 0)


def test_a_slot_directory_others_may_write_to_is_refused(tmp_path):
    """On a shared /tmp a stranger's (or a world-writable) directory must not hold the slots."""
    shared = tmp_path / "slots"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)
    with pytest.raises(OSError, match="not a directory of this user's alone"):
        ComputeSlots(shared, 2)
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    (tmp_path / "elsewhere").mkdir(mode=0o700)
    with pytest.raises(OSError, match="not a directory of this user's alone"):
        ComputeSlots(link, 2)


def test_closing_lets_go_of_the_slot_once(tmp_path):
    first = ComputeSlots(tmp_path / "slots", 1)
    first.__enter__()
    first.close()  # (a held slot is let go with its file)
    first.close()
    second = ComputeSlots(tmp_path / "slots", 1)
    assert second.try_take()
    second.close()
