"""swarmmap's own consensus rules as plug-ins (``pyproject.toml``'s ``swarmmap.consensus`` entry
points name these specs); each rule's module, and torch, is imported when a node makes one."""

from __future__ import annotations

from swarmmap.shared.plugins import ConsensusPlugin


def _dinno(model, settings):
    from swarmmap.services.learner.consensus.dinno import DinnoRule

    return DinnoRule()


def _ramen(model, settings):
    from swarmmap.services.learner.consensus.ramen import RamenRule

    return RamenRule(sum(p.numel() for p in model.parameters()), next(model.parameters()).device)


def _sigma(model, settings):
    from swarmmap.services.learner.consensus.sigma import SigmaRule

    return SigmaRule(model, settings.min_weight, settings.memory_rounds, settings.max_weight)


def _dgvi(model, settings):
    from swarmmap.services.learner.consensus.dgvi import DgviRule

    return DgviRule(model)


POSTERIOR = "weighs by the posterior's sigma"
DINNO = ConsensusPlugin(_dinno, "DiNNO's consensus exactly: every parameter pulled alike")
RAMEN = ConsensusPlugin(_ramen, "RAMEN's gradient counts, sent in the State after the parameters", extra_vector=True)
SIGMA = ConsensusPlugin(_sigma, "the Bayesian network's own posterior sigma (knobs: consensus_min_weight, sigma_memory_rounds, "
                                "sigma_max_weight)", models=("bnn",), why_models=POSTERIOR)
DGVI = ConsensusPlugin(_dgvi, "DGVI's precision-weighted pool of the neighbourhood's Gaussians", models=("bnn",),
                       why_models=POSTERIOR)
