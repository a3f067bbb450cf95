"""A robot's training points as its lidar streamer sends them (``robots/<i>/samples``).

Offline it keeps every scan's points until the traversal ends; online only the newest
``window_scans`` scans' (DiNNO's sliding window), so that a long traversal does not grow the
learner's memory without bound. A scan is taken once: Samples whose sequence number it has
taken already (a restarted world drives its traversal again from the start) are dropped and
counted (``repeated``), so a restart leaves the training points those of a clean run.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import numpy as np

from swarmmap.services.learner.errors import LearnerError
from swarmmap.shared.run.config import LearnerSettings
from swarmmap.shared.wire.protocol import Samples

log = logging.getLogger("learner")


class Collector:
    """Buffers a robot's Samples until the one marked ``last``: every scan's, or the newest ``keep``."""

    def __init__(self, keep: int | None = None) -> None:
        self.points: deque[np.ndarray] = deque(maxlen=keep)
        self.labels: deque[np.ndarray] = deque(maxlen=keep)
        self.legs: deque[int] = deque(maxlen=keep)  # exploration: each scan's leg of the drive (0 outside one)
        self.leg_done = -1  # exploration: the newest leg whose last scan came
        self.done = threading.Event()
        self.first = threading.Event()
        self.refused = 0  # Samples after the one marked last
        self.repeated = 0  # Samples of a scan taken already (a restarted world's)
        self.newest_seq = -1
        self.position: tuple[float, float] | None = None  # where the robot was at its newest scan
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)

    def add(self, msg: Samples) -> None:
        with self._lock:
            if self.done.is_set():  # the traversal is over: nothing may be added to it
                if self.refused == 0:
                    log.warning("refused Samples of robot %d after its last one (seq %d); further ones are only counted",
                                msg.sender, msg.seq)
                self.refused += 1
                return
            if msg.seq <= self.newest_seq:
                if self.repeated == 0:
                    log.warning("robot %d: Samples of scan %d again, after scan %d (the world restarted its traversal?): "
                                "dropped until a new scan comes; further ones are only counted", msg.sender, msg.seq,
                                self.newest_seq)
                self.repeated += 1
                return
            self.newest_seq = msg.seq
            self.points.append(msg.points.numpy())
            self.labels.append(msg.labels.numpy())
            self.legs.append(msg.leg or 0)
            self.position = (float(msg.position[0]), float(msg.position[1]))
            if msg.leg_end and msg.leg is not None:
                self.leg_done = max(self.leg_done, msg.leg)
            if msg.last:
                self.done.set()
            self._changed.notify_all()
        self.first.set()

    def wait(self, s: LearnerSettings, key: str, stop: threading.Event, who: str = "learner",
             online: bool | None = None, through_leg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Wait for the end of the traversal (``online``, default ``learner.data`` online: its first
        scan) and return the points so far (online: of the newest ``window_scans`` scans; exploring:
        of legs up to ``through_leg``); ``key`` names where they come from."""
        online = s.data == "online" if online is None else online
        ready = self.first if online else self.done
        deadline = time.monotonic() + s.collect_timeout_s
        while not ready.is_set() and not stop.is_set() and time.monotonic() < deadline:
            ready.wait(0.1)  # a stop (Ctrl-C, the run's end) is heard at once
        if not (ready.is_set() or stop.is_set()):
            what = "no Samples" if online else "no Samples with last=true"
            raise LearnerError(f"{who}: {what} on {key} within {s.collect_timeout_s:.0f} s", 3)
        if stop.is_set():
            raise InterruptedError
        points, labels = self.arrays(s.window_scans if online else None, through_leg)
        if len(points) == 0:
            raise LearnerError(f"{who}: the traversal ended without a single training point", 3)
        return points, labels

    def wait_leg(self, leg: int, timeout: float, stop: threading.Event) -> bool:
        """Wait (up to ``timeout``) for the last scan of ``leg`` (or of the whole drive); whether it came."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while self.leg_done < leg and not self.done.is_set() and not stop.is_set() and time.monotonic() < deadline:
                self._changed.wait(0.2)
            return self.leg_done >= leg or self.done.is_set()

    def arrays(self, last_scans: int | None = None, through_leg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every point so far, or those of the ``last_scans`` most recent scans (of legs up to ``through_leg``)."""
        with self._lock:
            points, labels = list(self.points), list(self.labels)
            if through_leg is not None:
                n = sum(1 for leg in self.legs if leg <= through_leg)  # (legs come in order)
                points, labels = points[:n], labels[:n]
            if not points:
                return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
            k = len(points) if last_scans is None else min(last_scans, len(points))
            return np.concatenate(points[len(points) - k :]), np.concatenate(labels[len(points) - k :])
