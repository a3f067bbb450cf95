"""Robust consensus: a member of the run that lies can neither pass for honest nor pull the team far.

Honest neighbours differ from a node by what their data taught them, and, round by round, by
about as much as each other. Two defences use that, block by block (each parameter tensor of
each copy in the State: a Bayesian layer's means and rho apart, a tracker's or counts' own):

- :class:`RoundScreen` judges a round's States together before the node update: a State one of
  whose blocks lies more than ``spread_factor`` times the round's honest spread from this node's
  (the median over the neighbours' States of the round, with at least :data:`MIN_NEIGHBOURS` of
  them; with two, as on a ring, the nearer one's: one of the two may lie; with one, no State is
  an outlier of anything) is left out of the round and
  counted as refused (``outlier``); a neighbour that sends only such States is left out as Algorithm
  1 leaves out any that sends only refused ones. A random direction at 0.45 of the norm, a layer's
  sign flipped, the vector scaled, a rho lowered by 2: each puts some block many times the honest
  spread away.
- :class:`PullBound` bounds what the accepted States can do (ClippedGossip, He, Karimireddy &
  Jaggi 2022): each link's difference from this node, per block, is clipped to ``pull_factor``
  times the median over the links, and so is each link's dual (a dual a liar keeps pushing would
  grow without bound, never cancelled by the other end of the link).

With an honest majority among a node's neighbours (and at least MIN_NEIGHBOURS of them) a liar is
an outlier; with two (a ring), a liar is an outlier of its honest fellow's spread (an honest
neighbour farther than ``spread_factor`` times the other is left out of that round only); with
one, only the per-State checks (:mod:`~swarmmap.services.learner.screening`) apply. A spread remembered from earlier rounds would
not do: the honest spread grows fastest in the first rounds (at round 0 the States are identical),
so an old one refuses honest neighbours.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from swarmmap.shared.learning.layout import StateLayout

log = logging.getLogger("learner")
MIN_NEIGHBOURS = 3  # a round's honest spread is the median of at least this many neighbours' States


def block_ids(layout: StateLayout, copies: int | None = None) -> tuple[np.ndarray, list[str]]:
    """The block of every value of a State (or of its first ``copies`` copies), and the blocks' names."""
    end = layout.size if copies is None else copies * layout.param_count
    blocks = [(name, segs) for name, segs in layout.blocks() if segs[0][0] < end]
    ids = np.full(end, -1, np.int64)
    for k, (_, segs) in enumerate(blocks):
        for at, n in segs:
            ids[at : at + n] = k
    assert (ids >= 0).all(), "every value of a State lies in a block"
    return ids, [name for name, _ in blocks]


class RoundScreen:
    """``screen(own, {neighbour: State})``: the neighbours whose State of the round is an outlier, and why."""

    def __init__(self, layout: StateLayout, spread_factor: float = 4.0):
        self.ids, self.names = block_ids(layout, copies=1)  # the parameters (a tracker or counts differ by data)
        self.n = layout.param_count
        self.counts = np.bincount(self.ids, minlength=len(self.names)).astype(np.float64)
        self.factor = spread_factor
        self.warned = False

    def deviations(self, own: np.ndarray, theirs: np.ndarray) -> np.ndarray:
        """Per block, the root mean square of ``theirs - own``."""
        diff = theirs.astype(np.float64) - own
        return np.sqrt(np.bincount(self.ids, weights=diff * diff, minlength=len(self.names)) / self.counts)

    def __call__(self, own: np.ndarray, peers: dict[int, np.ndarray]) -> dict[int, str]:
        if not peers:
            return {}
        own = own[: self.n]
        dev = {j: self.deviations(own, v[: self.n]) for j, v in peers.items() if v.shape[0] >= self.n}
        if len(dev) < 2:
            if not self.warned:
                self.warned = True
                log.info("one neighbour's State: no spread to judge it by; only each State's own checks apply")
            return {}
        scale = np.sqrt(np.bincount(self.ids, weights=own.astype(np.float64) ** 2, minlength=len(self.names)) / self.counts)
        floor = 1e-3 * scale + 1e-7  # identical States (round 0) have no spread: a floor, not zero
        devs = np.stack(list(dev.values()))
        # Two neighbours (a ring): the nearer one's, since one may lie; more: their median.
        reference = np.maximum(devs.min(axis=0) if len(dev) < MIN_NEIGHBOURS else np.median(devs, axis=0), floor)
        refused = {}
        for j, d in dev.items():
            ratio = d / (self.factor * reference)
            worst = int(np.argmax(ratio))
            if ratio[worst] > 1:
                refused[j] = (f"its {self.names[worst]} lies {d[worst] / reference[worst]:.1f} x the round's spread from "
                              f"this node's (limit {self.factor:g})")
        return refused


class PullBound:
    """Each link's pull and dual, per block, clipped to ``factor`` times the median over the links."""

    def __init__(self, layout: StateLayout, factor: float = 3.0, device: torch.device | str = "cpu", whole_state: bool = False):
        """Rows are the model's parameters, or (``whole_state``) whole States (DSGT's carry the tracker)."""
        end = layout.size if whole_state else layout.param_count
        self.blocks = [[(at, n) for at, n in segs] for _, segs in layout.blocks() if segs[0][0] < end]
        self.ids = torch.from_numpy(block_ids(layout, copies=None if whole_state else 1)[0]).to(device)
        self.factor = factor
        self.clipped = 0  # (link, block) pulls or duals clipped so far

    def _scales(self, rows: torch.Tensor) -> torch.Tensor | None:
        """Per row and value, the factor that brings each of the row's blocks within the bound (None: all within)."""
        if len(rows) < MIN_NEIGHBOURS:
            return None
        norms = torch.stack([torch.sqrt(sum(torch.square(rows[:, at : at + n]).sum(1) for at, n in segs)) for segs in self.blocks],
                            dim=1)  # (block by block: the same sums on every device)
        bound = self.factor * torch.quantile(norms, 0.5, dim=0)
        over = norms > bound
        if not bool(over.any()):
            return None
        self.clipped += int(over.sum())
        scale = torch.where(over, bound / norms.clamp(min=1e-30), torch.ones_like(norms))
        return scale[:, self.ids]

    def rows(self, th_i: torch.Tensor, thj: torch.Tensor) -> torch.Tensor:
        """The neighbours' parameters (one row each), each row's difference from ``th_i`` clipped."""
        scale = self._scales(thj - th_i)
        return thj if scale is None else th_i + scale * (thj - th_i)

    def duals(self, duals: dict[int, torch.Tensor]) -> None:
        """Clip each link's dual in place."""
        ids = sorted(duals)
        if len(ids) < MIN_NEIGHBOURS:
            return
        scale = self._scales(torch.stack([duals[j] for j in ids]))
        if scale is not None:
            for row, j in enumerate(ids):
                duals[j] = duals[j] * scale[row]
