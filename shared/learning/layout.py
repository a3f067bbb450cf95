"""What a State's vector holds, for everyone who reads one: learners, the codec, the observer.

A State is one float32 vector: the model's parameters, flattened in ``model.parameters()``
order (DiNNO's ``parameters_to_vector``), then as many parameter-sized vectors again as the
learning rule carries beside them: DSGT its gradient tracker, RAMEN's consensus its gradient
counts (:func:`state_copies`). Each weight matrix lies row-major at its offset
(:attr:`StateLayout.matrices`, what a low-rank State compresses).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from swarmmap.shared.plugins import load

if TYPE_CHECKING:
    from torch import nn

# Learning rules whose State carries a second parameter-sized vector after the parameters (a consensus
# rule says so itself: its plug-in's extra_vector).
EXTRA_VECTOR_ALGORITHMS = {"dsgt"}


def state_copies(algorithm: str, consensus: str) -> int:
    """How many parameter-sized vectors a State of this rule holds (1, or 2 with a tracker or counts)."""
    extra = algorithm in EXTRA_VECTOR_ALGORITHMS or (algorithm == "dinno" and load("consensus", consensus).extra_vector)
    return 2 if extra else 1


@dataclass(frozen=True)
class StateLayout:
    """A State's vector: ``copies`` x ``param_count`` values, the parameters first."""

    param_count: int
    copies: int = 1
    matrices: tuple[tuple[int, int, int], ...] = ()  # (offset, rows, cols) of each weight matrix
    tensors: tuple[tuple[str, int, int], ...] = ()  # (name, offset, size) of each parameter tensor

    @classmethod
    def of(cls, model: nn.Module, copies: int = 1) -> StateLayout:
        """The layout of ``model``'s States with ``copies`` parameter-sized vectors."""
        matrices, tensors, at = [], [], 0
        for name, p in model.named_parameters():
            if p.dim() == 2:
                matrices.append((at, int(p.shape[0]), int(p.shape[1])))
            tensors.append((name, at, p.numel()))
            at += p.numel()
        return cls(at, copies, tuple(matrices), tuple(tensors))

    def blocks(self) -> list[tuple[str, list[tuple[int, int]]]]:
        """The parts a neighbour's State is judged by, each (name, [(offset, size), ...]): a
        layer's weights and bias together, a Bayesian layer's means and rho apart, in every copy
        of the State (a tracker's or counts' own)."""
        groups: dict[str, list[tuple[int, int]]] = {}
        for name, at, n in self.tensors:
            layer, _, kind = name.rpartition(".")
            groups.setdefault(f"{layer or kind}{' rho' if kind.endswith('_rho') else ''}", []).append((at, n))
        if not groups:
            groups = {"state": [(0, self.param_count)]}
        out = []
        for c in range(self.copies):
            tag = "" if c == 0 else f" (copy {c + 1})"
            out += [(name + tag, [(c * self.param_count + at, n) for at, n in segs]) for name, segs in groups.items()]
        return out

    @property
    def size(self) -> int:
        """Values in a State."""
        return self.copies * self.param_count

    def params_of(self, state: np.ndarray) -> np.ndarray:
        """The model parameters inside a State (a view)."""
        return state[: self.param_count]

    def extra_of(self, state: np.ndarray) -> np.ndarray:
        """What comes after the parameters (a view; empty with one copy)."""
        return state[self.param_count :]

    def refuses(self, size: int) -> str | None:
        """Why a State of ``size`` values cannot be of this layout, or None."""
        return None if size == self.size else f"a State of {size} values, this run's States have {self.size}"
