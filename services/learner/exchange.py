"""What the two ways of exchanging States share: a node's rules, its counters and its refusals.

Algorithm 1 (:mod:`~swarmmap.services.learner.algorithm1`, by rounds) and the clock mode
(:mod:`~swarmmap.services.learner.clock`, ``learner.exchange_every_s``) take the same
:class:`ExchangeRules`, count into the same :class:`ExchangeStats` and refuse States through
:func:`refuse`: the first refusal of each kind per sender is logged, the others are counted.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from swarmmap.services.learner.transport import Envelope

log = logging.getLogger("learner")

# A State of a round further ahead than this cannot be needed yet (a neighbour is at most one
# round ahead of a node it waits for); it is refused, so that memory stays bounded.
ROUNDS_AHEAD = 2
CHECK_EVERY_S = 0.5  # how often a waiting node looks for neighbours gone or silent

# check(theirs, own) -> why a neighbour's State is refused, or None (own None: no reference to judge distance by)
StateCheck = Callable[[np.ndarray, "np.ndarray | None"], "str | None"]
# update(round, own State, {neighbour: its State of that round}) -> the node's next State
NodeUpdate = Callable[[int, np.ndarray, dict[int, np.ndarray]], np.ndarray]
# screen(own State, {neighbour: its State of the round}) -> {neighbour: why refused} (the round's States judged together)
RoundCheck = Callable[[np.ndarray, dict[int, np.ndarray]], dict[int, str]]
# rejoin(own State, {neighbour: State}) -> the State a node goes on from after catching up with its team
Rejoin = Callable[[np.ndarray, dict[int, np.ndarray]], np.ndarray]


@dataclass(frozen=True)
class ExchangeRules:
    """How long a node waits, resends and remembers (seconds unless named otherwise).

    ``peer_timeout``: fail when no neighbour is left for this long. ``resend_after``: send this
    round's messages again after this long without progress. ``linger``: after the last round,
    wait this long for the neighbours' final States. ``silent_after``: leave out a neighbour
    silent this long. ``rejoin_wait``: wait this long for a neighbour whose liveliness token
    vanished. ``keep_rounds``: rounds of own States kept for neighbours that replay them.
    ``round_wait`` (poor links, 0: off): a round waits at most this long for messages."""

    peer_timeout: float = 120.0
    resend_after: float = 2.0
    linger: float = 5.0
    silent_after: float = 30.0
    rejoin_wait: float = 0.0
    keep_rounds: int = 0
    round_wait: float = 0.0


class PeerFailure(RuntimeError):
    """A neighbour this node still needs is gone or silent."""


@dataclass
class ExchangeStats:
    """Time spent waiting for peers and sending, per node, accumulated over rounds; States refused."""

    wait_s: float = 0.0
    send_s: float = 0.0
    update_s: float = 0.0  # in node updates (a compute slot's wait included)
    rounds_done: int = 0
    resends: int = 0
    final_peers: dict[int, np.ndarray] = field(default_factory=dict)
    refused: Counter[str] = field(default_factory=Counter)
    refused_from: Counter[int] = field(default_factory=Counter)  # the same, per neighbour
    logged: set[tuple[str, int]] = field(default_factory=set)
    left_out: int = 0  # times a neighbour was left out of a round (gone or silent)
    rejoined: int = 0  # times one came back
    caught_up: int = 0  # times this node jumped ahead to its team's round
    replayed: int = 0  # States sent again to neighbours that were behind
    missed: int = 0  # neighbours' States a round went on without (round_wait: poor links)


def refuse(stats: ExchangeStats, node_id: int, msg: Envelope, why: str, reason: str) -> None:
    """Count a refused State; log the first of each reason per sender."""
    stats.refused[reason] += 1
    stats.refused_from[msg.sender] += 1
    if (reason, msg.sender) not in stats.logged:
        stats.logged.add((reason, msg.sender))
        log.warning("node %d: refused the %s of node %d for round %d: %s (further ones are only counted)", node_id,
                    msg.kind, msg.sender, msg.round, why)
