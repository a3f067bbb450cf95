"""What a learner reports of itself: validation loss and DiNNO's consensus error."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from swarmmap.shared.learning.bnn import BayesNet, DropoutPlan
from swarmmap.shared.learning.models import DropoutNet

CHUNK = 8192  # points a deterministic network's forward pass takes at once


@torch.no_grad()
def validation_bce(model: torch.nn.Module, points: torch.Tensor, labels: torch.Tensor, batch: int = 65536) -> float:
    """Mean binary cross-entropy of ``model`` over a validation set (for a Bayesian or MC-dropout
    network, of its prediction: the mean of the sampled passes' probabilities, 10 passes)."""
    total = 0.0
    for s in range(0, len(points), batch):
        xy, y = points[s : s + batch], labels[s : s + batch]
        if isinstance(model, DropoutNet):  # one mask per pass for the batch, as its maps draw them
            plan = DropoutPlan(model, 10, torch.Generator(device=xy.device).manual_seed(s))
            p = torch.cat([torch.sigmoid(plan.logits(xy[c : c + 4096])).mean(0) for c in range(0, len(xy), 4096)])
            total += float(F.binary_cross_entropy(p.clamp(1e-7, 1 - 1e-7), y, reduction="sum"))
        elif isinstance(model, BayesNet):
            with model.noise(seed=s):
                p = torch.stack([model(xy) for _ in range(10)]).mean(0).clamp(1e-7, 1 - 1e-7)
            total += float(F.binary_cross_entropy(p, y, reduction="sum"))
        else:  # (the logits in chunks: a FourierNet's features of 65,536 points at once are 128 MiB a layer)
            logits = torch.cat([model.logits(xy[c : c + CHUNK]) for c in range(0, len(xy), CHUNK)])
            total += float(F.binary_cross_entropy_with_logits(logits, y, reduction="sum"))
    return total / max(len(points), 1)


def consensus_error(theta_i: np.ndarray, peers: dict[int, np.ndarray]) -> float:
    """DiNNO's consensus metric for one node: mean distance between its unit-normalised
    parameter vector and its neighbours' (0 with no neighbours)."""
    if not peers:
        return 0.0
    a = theta_i / max(np.linalg.norm(theta_i), 1e-12)
    return float(np.mean([np.linalg.norm(a - p / max(np.linalg.norm(p), 1e-12)) for p in peers.values()]))
