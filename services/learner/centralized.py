"""The centralized baseline: one model trained on every robot's points, reported as every robot's.

DiNNO's upper reference: no communication at all, one process (``learner.transport`` inproc)
holding the whole team's data. The first robot's learner trains it; every robot then reports
its metrics and writes its outputs with that one model.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from swarmmap.services.learner.transport import MemoryHub

log = logging.getLogger("learner")


def train_centralized(learners: list, stop: threading.Event) -> None:
    """Train one model on the points of every learner in ``learners`` (RobotLearners, prepared)."""
    for r in learners:  # each robot's own node and checkpoint, as for any run (a restarted learner resumes)
        r.compose(None)
    head = learners[0]
    head.points = np.concatenate([r.points for r in learners])
    head.labels = np.concatenate([r.labels for r in learners])
    head.graph, head.neighbours = {head.robot: set()}, set()
    head.compose(None, resume=False)
    log.info("centralized: one model on %d points of %d robots", len(head.points), len(learners))
    head.train(MemoryHub({head.robot: set()}).transport(head.robot), stop)
    final = head.node.state()
    for r in learners[1:]:
        r.node, r.points, r.t_start, r.rounds = head.node, head.points, head.t_start, head.rounds
        r.finish(final, {})
