"""The learning rules by name (``learner.algorithm``): the one place a name becomes a node.

``dinno`` (and the two baselines without communication, ``individual`` and ``centralized``,
whose graph has no edges) is :class:`~swarmmap.services.learner.dinno.DinnoNode` with the
consensus rule and regularisation the settings name; ``dsgd`` and ``dsgt`` are DiNNO's
baselines (:mod:`~swarmmap.services.learner.baselines`) with Metropolis weights on the graph.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from swarmmap.services.learner.baselines import DsgdNode, DsgtNode
from swarmmap.services.learner.consensus import consensus_rule
from swarmmap.services.learner.dinno import DinnoNode
from swarmmap.services.learner.node import Node, NodeInputs, coverage_for
from swarmmap.services.learner.regularization import regularization
from swarmmap.services.learner.robust import PullBound
from swarmmap.services.learner.settings import (
    ConsensusSettings,
    DinnoSettings,
    RegularizationSettings,
    RobustSettings,
    TrainingSettings,
)
from swarmmap.shared.learning.graphs import metropolis_weights
from swarmmap.shared.learning.layout import StateLayout, state_copies
from swarmmap.shared.run.config import LearnerSettings


@dataclass(frozen=True)
class RuleChoice:
    """What picks and sets up a node beyond its inputs: the rule's settings and the graph."""

    dinno: DinnoSettings
    consensus: str
    consensus_settings: ConsensusSettings
    regularization: RegularizationSettings
    graph: dict[int, set[int]]
    robot: int
    public: Callable[[], np.ndarray | None] | None = None  # what the neighbours hold of this node's State
    robust: RobustSettings = RobustSettings()

    @classmethod
    def of(cls, s: LearnerSettings, graph: dict[int, set[int]], robot: int,
           public: Callable[[], np.ndarray | None] | None = None) -> RuleChoice:
        return cls(DinnoSettings.of(s), s.consensus, ConsensusSettings.of(s), RegularizationSettings.of(s), graph, robot, public,
                   RobustSettings.of(s))

    def bound(self, inputs: NodeInputs, whole_state: bool = False) -> PullBound | None:
        """Robust consensus's bound on each link's pull (None when off)."""
        if not self.robust.on:
            return None
        return PullBound(inputs.layout, self.robust.pull_factor, next(inputs.model.parameters()).device, whole_state)


def _dinno(inputs: NodeInputs, c: RuleChoice) -> Node:
    rule = consensus_rule(c.consensus, inputs.model, c.consensus_settings)
    return DinnoNode(inputs, c.dinno, rule, regularization(inputs.model, c.regularization), c.public, c.bound(inputs))


NODES: dict[str, Callable[[NodeInputs, RuleChoice], Node]] = {
    "dinno": _dinno,
    "individual": _dinno,
    "centralized": _dinno,
    "dsgd": lambda inputs, c: DsgdNode(inputs, metropolis_weights(c.graph, c.robot), c.robot, c.bound(inputs)),
    "dsgt": lambda inputs, c: DsgtNode(inputs, metropolis_weights(c.graph, c.robot), c.robot, c.bound(inputs, whole_state=True)),
}


def make_node(algorithm: str, inputs: NodeInputs, choice: RuleChoice) -> Node:
    """The node of ``algorithm`` (``learner.algorithm``)."""
    if algorithm not in NODES:
        raise ValueError(f"unknown algorithm {algorithm!r}; known: {', '.join(NODES)}")
    return NODES[algorithm](inputs, choice)


def node_inputs(s: LearnerSettings, model, points: np.ndarray, labels: np.ndarray, seed: int,
                bounds: tuple[float, float, float, float] | None = None) -> NodeInputs:
    """What a node of the learner's settings ``s`` is made of (its State buffer: a plain vector)."""
    training = TrainingSettings.of(s)
    layout = StateLayout.of(model, state_copies(s.algorithm, s.consensus))
    points, labels = np.asarray(points), np.asarray(labels)
    return NodeInputs(model, points, labels, training, seed, layout, coverage_for(model, training, s.unseen_margin_m, bounds, points))


def node_for(s: LearnerSettings, model, points: np.ndarray, labels: np.ndarray, seed: int, *,
             bounds: tuple[float, float, float, float] | None = None, graph: dict[int, set[int]] | None = None,
             robot: int = 0) -> Node:
    """A node of the learner's settings ``s`` on these points, as the learner composes one (no links)."""
    inputs = node_inputs(s, model, points, labels, seed, bounds)
    return make_node(s.algorithm, inputs, RuleChoice.of(s, graph if graph is not None else {robot: set()}, robot))
