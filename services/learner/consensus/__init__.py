"""Consensus rules, one class a module, and the registry that names them (``learner.consensus``).

See :mod:`.base` for what a rule is and how to add one.
"""

from __future__ import annotations

import torch

from swarmmap.services.learner.consensus.base import ConsensusRule
from swarmmap.services.learner.consensus.dgvi import DgviRule
from swarmmap.services.learner.consensus.dinno import DinnoRule
from swarmmap.services.learner.consensus.ramen import RamenRule
from swarmmap.services.learner.consensus.sigma import SigmaRule
from swarmmap.services.learner.settings import ConsensusSettings

# name -> rule(model, settings): the one place a rule's name becomes its class
RULES = {
    "dinno": lambda model, s: DinnoRule(),
    "ramen": lambda model, s: RamenRule(sum(p.numel() for p in model.parameters()), next(model.parameters()).device),
    "sigma": lambda model, s: SigmaRule(model, s.min_weight, s.memory_rounds, s.max_weight),
    "dgvi": lambda model, s: DgviRule(model),
}


def consensus_rule(name: str, model: torch.nn.Module, settings: ConsensusSettings) -> ConsensusRule:
    """The rule called ``name`` for one node's ``model``."""
    if name not in RULES:
        raise ValueError(f"unknown consensus rule {name!r}; known: {', '.join(RULES)}")
    return RULES[name](model, settings)
