"""Which neighbour States a node takes: the defence against a member that sends garbage.

Honest neighbours start from the same initialisation and consensus keeps them close, so a State
whose parameters are not finite, constant (e.g. all zero) or farther from this node's own than
``max_distance`` times the norm of its own is refused (:func:`implausible`). Without a reference
(a node catching up with its team holds stale parameters) only the tests that need none apply.
:class:`StateScreen` is the learner's check: a State's size first, then its parameters.
"""

from __future__ import annotations

import numpy as np

from swarmmap.shared.layout import StateLayout


def implausible(theirs: np.ndarray, own: np.ndarray | None, max_distance: float) -> str | None:
    """Why a neighbour's parameters cannot come from an honest node, or None."""
    if own is not None and theirs.shape != own.shape:
        return f"{theirs.size} parameters, expected {own.size}"
    if not np.isfinite(theirs).all():
        return "non-finite parameters"
    if theirs.size > 1 and np.ptp(theirs) == 0:
        return f"constant parameters ({float(theirs[0]):g} everywhere)"
    if own is None:
        return None
    scale = float(np.linalg.norm(own))
    distance = float(np.linalg.norm(theirs.astype(np.float64) - own))
    if scale > 0 and distance > max_distance * scale:
        return f"parameters {distance / scale:.2f} x the own parameters' norm away (limit {max_distance:g})"
    return None


class StateScreen:
    """``screen(theirs, own)``: why a neighbour's State is refused, or None. DSGT's States carry
    its gradient tracker and RAMEN's its counts too: the parameters are judged."""

    def __init__(self, layout: StateLayout, max_distance: float):
        self.layout, self.max_distance = layout, max_distance

    def __call__(self, theirs: np.ndarray, own: np.ndarray | None) -> str | None:
        if theirs.size != self.layout.size:
            return f"{theirs.size} values, this node's State has {self.layout.size}"
        params_of = self.layout.params_of
        return implausible(params_of(theirs), None if own is None else params_of(own), self.max_distance)
