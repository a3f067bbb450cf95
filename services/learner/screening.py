"""Which neighbour States a node takes, each on its own: the first defence against a member that
sends garbage (the round's States are then judged together: :mod:`~swarmmap.services.learner.robust`).

Honest neighbours start from the same initialisation and consensus keeps them close, so a State
whose parameters are not finite, constant (e.g. all zero) or farther from this node's own than
``max_distance`` times the norm of its own is refused (:func:`implausible`), and so, by the
learner's screen, is one whose norm differs from its own by more than MAX_NORM_RATIO either way
(:func:`other_norm`: a vector scaled within the distance limit). A Bayesian
network's means and rho are also judged apart, each against its own norm (at GROUP_FACTOR times
the distance: early in training the means move fast for their size): its rho, about -5 each,
makes up almost all of the whole norm and would hide any move of the means. Every State is judged against the node's own
parameters, also when they are a few rounds old (a node that resumed or caught up with its team).
:class:`StateScreen` is the learner's check: a State's size, whatever it carries after the
parameters finite, then its parameters.
"""

from __future__ import annotations

import numpy as np

from swarmmap.shared.learning.bnn import is_rho
from swarmmap.shared.learning.layout import StateLayout

GROUP_FACTOR = 4  # a Bayesian network's means (or rho) may lie this many times max_distance of their own norm away


MAX_NORM_RATIO = 1.25  # a neighbour's parameters' norm against this node's own, either way


def implausible(theirs: np.ndarray, own: np.ndarray | None, max_distance: float) -> str | None:
    """Why a neighbour's parameters cannot come from an honest node, or None."""
    if own is not None and theirs.shape != own.shape:
        return f"{theirs.size} parameters, expected {own.size}"
    if not np.isfinite(theirs).all():
        return "non-finite parameters"
    if theirs.size > 1 and np.ptp(theirs) == 0:
        return f"constant parameters ({float(theirs[0]):g} everywhere)"
    return None if own is None else too_far(theirs, own, max_distance)


def other_norm(theirs: np.ndarray, own: np.ndarray) -> str | None:
    """Why ``theirs`` has another norm than ``own`` by more than MAX_NORM_RATIO either way, or None.
    Neighbours that learn together keep their parameters' norms within a few percent of each other
    (0.1% at the end of a clean smoke run): a vector scaled by 1.45, which the distance limit of
    0.5 lets through, is not theirs. (Not for a neighbour back from learning apart: its norm may
    differ by far more, and the reunion's loose check skips this.)"""
    scale, norm = float(np.linalg.norm(own)), float(np.linalg.norm(theirs.astype(np.float64)))
    if scale > 0 and not 1 / MAX_NORM_RATIO <= norm / scale <= MAX_NORM_RATIO:
        return f"parameters of {norm / scale:.2f} x the own parameters' norm (limit {MAX_NORM_RATIO:g} either way)"
    return None


def too_far(theirs: np.ndarray, own: np.ndarray, max_distance: float) -> str | None:
    """Why ``theirs`` lies farther from ``own`` than ``max_distance`` times the norm of ``own``, or None."""
    scale = float(np.linalg.norm(own))
    distance = float(np.linalg.norm(theirs.astype(np.float64) - own))
    if scale > 0 and distance > max_distance * scale:
        return f"parameters {distance / scale:.2f} x the own parameters' norm away (limit {max_distance:g})"
    return None


def groups(layout: StateLayout) -> list[tuple[str, np.ndarray]]:
    """The parts of a State's parameters judged apart: a Bayesian network's means (with every
    other parameter) and its rho; a deterministic network's parameters as one."""
    rho = np.zeros(layout.param_count, bool)
    for name, at, n in layout.tensors:
        rho[at : at + n] = is_rho(name)
    if not rho.any():
        return [("parameters", np.arange(layout.param_count))]
    return [("means", np.flatnonzero(~rho)), ("rho", np.flatnonzero(rho))]


class StateScreen:
    """``screen(theirs, own)``: why a neighbour's State is refused, or None. DSGT's States carry
    its gradient tracker and RAMEN's its counts after the parameters: those must be finite."""

    def __init__(self, layout: StateLayout, max_distance: float, norms: bool = True):
        """``norms``: judge the parameters' norm against the own (not against own parameters
        rounds old, nor a neighbour back from learning apart: theirs may differ by far more)."""
        self.layout, self.max_distance, self.norms = layout, max_distance, norms
        self.groups = groups(layout)

    def loose(self, theirs: np.ndarray, own: np.ndarray | None) -> str | None:
        """The checks but the distance and the norm: why a State cannot come from an honest node
        however far apart the two have learnt (a neighbour back from a partition), or None."""
        return StateScreen(self.layout, np.inf, norms=False)(theirs, own)

    def clip(self, theirs: np.ndarray, own: np.ndarray) -> np.ndarray:
        """``theirs`` pulled toward ``own`` until it lies within every distance limit (the whole
        and, for a Bayesian network, each part): what a far State may move this node by, at most."""
        mine, yours = self.layout.params_of(own).astype(np.float64), self.layout.params_of(theirs).astype(np.float64)
        diff = yours - mine
        factor = 1.0
        limits = [(np.arange(mine.size), self.max_distance)] + (
            [(at, GROUP_FACTOR * self.max_distance) for _, at in self.groups] if len(self.groups) > 1 else [])
        for at, limit in limits:
            distance, scale = float(np.linalg.norm(diff[at])), float(np.linalg.norm(mine[at]))
            if distance > 0 and scale > 0:
                factor = min(factor, 0.99 * limit * scale / distance)
        if factor >= 1.0:
            return theirs
        out = theirs.copy()
        out[: mine.size] = (mine + factor * diff).astype(theirs.dtype)
        return out

    def __call__(self, theirs: np.ndarray, own: np.ndarray | None) -> str | None:
        if theirs.size != self.layout.size:
            return f"{theirs.size} values, this node's State has {self.layout.size}"
        extra = self.layout.extra_of(theirs)
        if extra.size and not np.isfinite(extra).all():
            return "non-finite values after the parameters"
        mine, yours = (None if own is None else self.layout.params_of(own)), self.layout.params_of(theirs)
        why = implausible(yours, mine, self.max_distance)
        if why is None and mine is not None and self.norms:
            why = other_norm(yours, mine)
        if why is not None or mine is None or len(self.groups) == 1:
            return why
        for name, at in self.groups:  # each part on the scale of its own norm, more loosely (early moves are large)
            why = too_far(yours[at], mine[at], GROUP_FACTOR * self.max_distance)
            if why is not None:
                return f"{name}: {why}"
        return None
