"""A robot's training points as its lidar streamer sends them (``robots/<i>/samples``)."""

from __future__ import annotations

import logging
import threading

import numpy as np

from swarmmap.shared.protocol import Samples

log = logging.getLogger("learner")


class Collector:
    """Buffers a robot's Samples until the one marked ``last``."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        self.done = threading.Event()
        self.first = threading.Event()
        self.refused = 0  # Samples after the one marked last
        self.position: tuple[float, float] | None = None  # where the robot was at its newest scan
        self._lock = threading.Lock()

    def add(self, msg: Samples) -> None:
        with self._lock:
            if self.done.is_set():  # the traversal is over: nothing may be added to it
                if self.refused == 0:
                    log.warning("refused Samples of robot %d after its last one (seq %d); further ones are only counted",
                                msg.sender, msg.seq)
                self.refused += 1
                return
            self.points.append(msg.points.numpy())
            self.labels.append(msg.labels.numpy())
            self.position = (float(msg.position[0]), float(msg.position[1]))
            if msg.last:
                self.done.set()
        self.first.set()

    def arrays(self, last_scans: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every point so far, or those of the ``last_scans`` most recent scans."""
        with self._lock:
            if not self.points:
                return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
            k = len(self.points) if last_scans is None else min(last_scans, len(self.points))
            return np.concatenate(self.points[-k:]), np.concatenate(self.labels[-k:])
