"""The learner's networks by name: build one from the run's settings, save it, load it back.

``fourier`` is DiNNO's FourierNet, ``bnn`` the paper's Bayesian network, ``dropout`` a
FourierNet with MC dropout (:mod:`~swarmmap.shared.learning.models`, :mod:`~swarmmap.shared.learning.bnn`);
each is a plug-in (:mod:`~swarmmap.shared.learning.kinds`), and another package adds its own.
Every learner of a run builds its network from the same seed, as in DiNNO. A saved model
(``RUN_DIR/models/robot-<i>.pt``) holds its kind, shape, scale and state dict, so that
:func:`load_model` needs nothing else.
"""

from __future__ import annotations

import io
from pathlib import Path

import torch
from torch import nn

from swarmmap.shared.learning.bnn import BayesNet
from swarmmap.shared.learning.models import DropoutNet
from swarmmap.shared.plugins import ModelPlugin, PluginError, load
from swarmmap.shared.run.atomic import atomic_write_bytes
from swarmmap.shared.run.config import NetworkSpec


def model_plugin(kind: str) -> ModelPlugin:
    """The installed network called ``kind`` (a ValueError naming the installed ones when none is)."""
    try:
        return load("models", kind)
    except PluginError as exc:
        raise ValueError(f"unknown model {kind!r}: {exc}") from None


def has_std(kind: str) -> bool:
    """Whether a model of ``kind`` is stochastic (:class:`StochasticNet`): its maps have a
    standard deviation (BNN, MC dropout); a FourierNet's have none."""
    return model_plugin(kind).std


def build_model(shape: list[int], scale: float, bounds: tuple[float, float, float, float], seed: int,
                kind: str = "fourier", prior_sigma: float = 0.1, rho_init: float = -5.0, dropout_p: float = 0.1,
                local_reparam: bool = False) -> nn.Module:
    """The network called ``kind`` (a model plug-in: fourier, bnn, dropout or one from another
    package) initialised from ``seed`` (every learner of a run starts from the same one, as in DiNNO)."""
    plugin = model_plugin(kind)
    spec = NetworkSpec(kind, tuple(shape), scale, prior_sigma, rho_init, dropout_p, local_reparam)
    gen_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        model = plugin.build(spec, bounds)
    finally:
        torch.random.set_rng_state(gen_state)
    model.swarmmap_model, model.swarmmap_shape = kind, list(shape)  # what save_model records (the spec, not the layers)
    return model


def build_network(spec: NetworkSpec, bounds: tuple[float, float, float, float], seed: int) -> nn.Module:
    """The network ``spec`` describes (:meth:`~swarmmap.shared.run.config.RunConfig.network`) for a map of ``bounds``."""
    return build_model(list(spec.shape), spec.scale, bounds, seed, spec.kind, spec.prior_sigma, spec.rho_init,
                       spec.dropout_p, spec.local_reparam)


def model_kind(model: nn.Module) -> str:
    """What :func:`build_model` called the model (``fourier``, ``bnn``, ``dropout``, a plug-in's name)."""
    if (kind := getattr(model, "swarmmap_model", None)) is not None:
        return kind
    return "bnn" if isinstance(model, BayesNet) else "dropout" if isinstance(model, DropoutNet) else "fourier"


def save_model(model: nn.Module, path: Path, **meta: object) -> None:
    """Write the model (kind, state dict, shape, scale, its kind's settings and ``meta``) atomically."""
    kind = model_kind(model)
    extra: dict = {}
    if kind == "bnn" and model.bayes_layers():
        extra = {"prior_sigma": model.bayes_layers()[0].prior_sigma}
    elif kind == "dropout":
        extra = {"dropout_p": model.p}
    buf = io.BytesIO()
    shape = getattr(model, "swarmmap_shape", model.shape)
    torch.save({"kind": kind, "shape": shape, "scale": model.scale, "state_dict": model.state_dict(),
                "meta": meta, **extra}, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_model(path: Path) -> nn.Module:
    """Load a model written by :func:`save_model`."""
    doc = torch.load(path, map_location="cpu", weights_only=True)
    model = build_model(doc["shape"], doc["scale"], (0.0, 0.0, 1.0, 1.0), 0, doc.get("kind", "fourier"),
                        doc.get("prior_sigma", 0.1), dropout_p=doc.get("dropout_p", 0.1))
    model.load_state_dict(doc["state_dict"])
    return model
