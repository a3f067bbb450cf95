"""A node's pace: how much of a round it trains and how much it waits for its neighbours' States,
and what follows from it.

A slow link (``learner.slow_link_compression``). When, over the last SLOW_WINDOW rounds, the node's
median wait for its neighbours' States was SLOW_RATIO times its median training (node update, a
compute slot's wait included) and at least SLOW_MIN_WAIT_S, the exchange and not the training sets
the pace: from then on its own States go out compressed, and it says so. Its neighbours rebuild
whatever encoding a sender chose, so one node switches on its own; it does not switch back.
Medians, not sums: one long wait (a partition, a neighbour restarting) is no slow link. A link
so slow that the median wait of a node's first SLOW_EARLY rounds is SLOW_CLEAR_S or more (an
uncompressed team on 1 Mbit/s links, where a round takes a minute) is judged then, not after
SLOW_WINDOW rounds. A
neighbour much slower to train than this node (a host with less CPU) also makes it wait;
compressing then buys nothing and costs a little accuracy (docs/deployment.md).

Resends do not follow the pace (rounds slowed by resends would stretch the resends, which would
slow the rounds more): a round's messages go again after ``resend_after`` seconds without
progress, then after twice as long each time, up to RESEND_BACKOFF times ``resend_after``, so a
round slower than that on a slow link costs a few copies of its messages, not one every few
seconds.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from collections.abc import Callable

log = logging.getLogger("learner")

SLOW_WINDOW = 20  # rounds judged together
SLOW_RATIO = 2.0  # median wait / median training beyond which the links set the pace
SLOW_MIN_WAIT_S = 0.25  # and a median wait of at least this (fast rounds wait a few ms, whatever the ratio)
SLOW_EARLY = 3  # rounds enough to judge when the median wait is SLOW_CLEAR_S or more
SLOW_CLEAR_S = 5.0  # a median wait of seconds a round: no need to wait for SLOW_WINDOW rounds to see it


class Pace:
    """One node's recent rounds: (wait, training) each, SLOW_WINDOW of them."""

    def __init__(self, node_id: int, slow_link: Callable[[], str] | None = None):
        """``slow_link()`` switches the node's States to a compressed encoding and names it (None: never)."""
        self.node_id, self.slow_link = node_id, slow_link
        self.recent: deque[tuple[float, float]] = deque(maxlen=SLOW_WINDOW)
        self.adapted: str | None = None

    def round_done(self, rnd: int, wait: float, busy: float) -> None:
        """Round ``rnd - 1`` waited ``wait`` seconds for messages and spent ``busy`` in its update."""
        if self.slow_link is None or self.adapted:
            return
        self.recent.append((wait, busy))
        if len(self.recent) < SLOW_EARLY:
            return
        waited, trained = (statistics.median(r[k] for r in self.recent) for k in (0, 1))
        if len(self.recent) < SLOW_WINDOW and waited < SLOW_CLEAR_S:
            return
        if waited >= SLOW_MIN_WAIT_S and waited >= SLOW_RATIO * trained:
            self.adapted = self.slow_link()
            log.warning("node %d: over its last %d rounds it waited a median %.2f s a round for its neighbours' States "
                        "against %.2f s of training: its links, not its training, set the pace; its States go out as "
                        "%s from round %d on (learner.slow_link_compression)", self.node_id, len(self.recent), waited, trained,
                        self.adapted, rnd)
