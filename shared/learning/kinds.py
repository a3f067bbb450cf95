"""swarmmap's own networks as plug-ins (``pyproject.toml``'s ``swarmmap.models`` entry points name
these specs): DiNNO's FourierNet, the paper's Bayesian network and MC dropout. torch and the
networks' modules are imported when a network is built, not when a config names one."""

from __future__ import annotations

from swarmmap.shared.plugins import ModelPlugin


def _fourier(spec, bounds):
    from swarmmap.shared.learning.models import FourierNet

    return FourierNet(list(spec.shape), spec.scale, bounds)


def _bnn(spec, bounds):
    from swarmmap.shared.learning.bnn import BayesNet

    return BayesNet(list(spec.shape), spec.scale, bounds, spec.prior_sigma, spec.rho_init, spec.local_reparam)


def _dropout(spec, bounds):
    from swarmmap.shared.learning.models import DropoutNet

    return DropoutNet(list(spec.shape), spec.scale, bounds, spec.dropout_p)


FOURIER = ModelPlugin(_fourier, "DiNNO's FourierNet: a sine layer, then ReLU layers")
BNN = ModelPlugin(_bnn, "the paper's Bayesian network: every weight a Gaussian (mu, rho)", std=True)
DROPOUT = ModelPlugin(_dropout, "a FourierNet with MC dropout", std=True)
