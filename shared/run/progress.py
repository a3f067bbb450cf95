"""A run's progress in one line, from what its services publish: the traversal from the world's
``Scan`` messages, the training from the learners' ``Metrics``. ``swarmmap up`` shows the line
on its console and the recorder writes it to its log (so compose and SLURM logs say it too).

    team = TeamProgress(robots=3, rounds=60)
    bus.subscribe(keys.metrics("*"), Metrics, team.add)
    print(team.line())   # training: round 20 of 60 (33%), val_bce mean 0.2113 (min 0.2010, max 0.2254), ETA 41 s
"""

from __future__ import annotations

import threading
import time

from swarmmap.shared.wire.protocol import Metrics, Scan

# How often a log (not a terminal) gets a progress line while the run goes.
PROGRESS_EVERY_S = 10.0


def duration(seconds: float) -> str:
    """``41 s``, ``3 min 20 s``, ``1 h 05 min``."""
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{int(seconds // 60)} min {int(seconds % 60):02d} s"
    return f"{int(seconds // 3600)} h {int(seconds % 3600 // 60):02d} min"


def time_left(done: float, total: float, seconds: float, at_least: float = 0.0) -> float | None:
    """Seconds until ``total`` at the pace so far (``done`` of it in ``seconds``); None while too
    little is done to tell (``done`` not above ``at_least``, or no time has passed). The one
    estimate of time left: up's and the recorder's line, the experiments' and the benches' use it."""
    if done <= at_least or seconds <= 0:
        return None
    return max(0.0, (total - done) * seconds / done)


def eta_words(seconds: float | None) -> str:
    """``ETA 41 s``, or that the time left is not known yet."""
    return "time left not known yet" if seconds is None else f"ETA {duration(seconds)}"


class TeamProgress:
    """The team's training at a glance: the slowest learner's round of ``rounds``, the mean,
    min and max of every learner's latest val_bce, and the time left at the slowest learner's
    pace. Thread-safe (Zenoh calls ``add`` from its threads)."""

    def __init__(self, robots: int, rounds: int):
        self.robots, self.rounds = robots, rounds
        self._lock = threading.Lock()
        self.latest: dict[int, Metrics] = {}
        self._first_seen: dict[int, tuple[float, int]] = {}  # when this process first heard of each learner, and its round
        self.updates = 0

    def add(self, m: Metrics, now: float | None = None) -> None:
        """Take one learner's Metrics (a late, older one is ignored)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if m.sender in self.latest and m.round < self.latest[m.sender].round:
                return
            self.latest[m.sender] = m
            self._first_seen.setdefault(m.sender, (now, m.round))
            self.updates += 1

    @property
    def started(self) -> bool:
        """Whether any learner has reported a round."""
        return bool(self.latest)

    def finished(self) -> int:
        """How many learners sent their final Metrics."""
        with self._lock:
            return sum(m.final for m in self.latest.values())

    def eta_s(self, now: float | None = None) -> float | None:
        """Seconds until the slowest learner reaches the last round, at its pace so far."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if not self.latest:
                return None
            slow = min(self.latest.values(), key=lambda m: m.round)
            t0, r0 = self._first_seen[slow.sender]
        # its pace as seen here (a resumed learner too), else by its own clock since it started training
        seen = time_left(slow.round - r0, self.rounds - r0, now - t0)
        return seen if seen is not None else time_left(slow.round, self.rounds, slow.wall_time_s)

    def line(self, now: float | None = None) -> str | None:
        """``training: round 20 of 60 (33%), val_bce mean 0.2113 (min 0.2010, max 0.2254), ETA 41 s``;
        None before the first Metrics."""
        with self._lock:
            if not self.latest:
                return None
            done = min(m.round for m in self.latest.values())
            losses = [m.val_bce for m in self.latest.values()]
            heard, final = len(self.latest), sum(m.final for m in self.latest.values())
        text = (f"training: round {done} of {self.rounds} ({100 * done / max(self.rounds, 1):.0f}%), val_bce mean "
                f"{sum(losses) / len(losses):.4f} (min {min(losses):.4f}, max {max(losses):.4f})")
        if heard < self.robots:
            text += f", {heard} of {self.robots} learners reporting"
        if final:
            text += f", {final} of {self.robots} finished"
        eta = self.eta_s(now)
        return text + (f", {eta_words(eta)}" if eta is not None and final < self.robots else "")


class TraversalProgress:
    """The robots' traversal: scans the world published per robot, and which robots are done
    (their last scan). ``expected`` (scans over every robot, from the paths) gives a share."""

    def __init__(self, robots: int, expected: int = 0):
        self.robots, self.expected = robots, expected
        self._lock = threading.Lock()
        self.scans: dict[int, int] = {}
        self.done: set[int] = set()
        self.t0: float | None = None
        self.t_done: float | None = None

    def add(self, scan: Scan, now: float | None = None) -> None:
        """Count one robot's scan."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if self.t0 is None:
                self.t0 = now
            self.scans[scan.sender] = self.scans.get(scan.sender, 0) + 1
            if scan.last:
                self.done.add(scan.sender)
                if len(self.done) >= self.robots and self.t_done is None:
                    self.t_done = now

    @property
    def started(self) -> bool:
        """Whether any scan came."""
        return self.t0 is not None

    @property
    def over(self) -> bool:
        """Whether every robot sent its last scan."""
        return self.t_done is not None

    def line(self, now: float | None = None) -> str | None:
        """``traversal: 1234 of about 3100 scans (40%), 1 of 3 robots done, 25 s``; None before the first scan."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if self.t0 is None:
                return None
            total, done = sum(self.scans.values()), len(self.done)
            elapsed = (self.t_done or now) - self.t0
        share = f" of about {self.expected} ({100 * min(total / self.expected, 1):.0f}%)" if self.expected else ""
        verb = "done" if self.t_done is not None else "so far"
        return f"traversal {verb}: {total} scans{share}, {done} of {self.robots} robots at the end of their paths, {duration(elapsed)}"
