"""Consensus rules, one class a module, each registered as a plug-in (``learner.consensus``).

The built-in rules' specs are in :mod:`.builtin`, named in swarmmap's ``pyproject.toml`` under the
entry-point group ``swarmmap.consensus`` exactly as a rule from another package is
(swarmmap.shared.plugins). See :mod:`.base` for what a rule is and docs/layout.md for adding one.
This package imports no torch: a config names a rule, and every service that validates one
loads its spec.
"""

from __future__ import annotations

from typing import Any

from swarmmap.shared.plugins import broken_contract, load

# what Algorithm 1's node update calls on a rule (services/learner/consensus/base.py)
RULE_METHODS = ("start_round", "keep_for", "targets", "dual_step", "data_loss", "extra")


def consensus_rule(name: str, model: Any, settings: Any) -> Any:
    """The rule called ``name`` for one node's ``model`` (a PluginError naming a part that cannot be had)."""
    rule = load("consensus", name).make(model, settings)
    missing = [m for m in RULE_METHODS if not callable(getattr(rule, m, None))]
    if missing:
        raise broken_contract(name, "consensus", f"the rule it makes has no {', '.join(missing)}")
    return rule
