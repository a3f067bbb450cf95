"""Implicit occupancy networks and what every user of a model needs: build, flatten, predict.

:class:`FourierNet` is DiNNO's network: a sine (SIREN) first layer, ReLU hidden layers and a
sigmoid output, mapping a world point (x, y) in metres to an occupancy probability. Inputs are
taken in metres from the map's centre (a fixed buffer, so a saved model is self-contained), so
the sine layer's ``scale`` means the same spatial frequency on every plan. Parameters travel
as one flat float32 vector (DiNNO's ``parameters_to_vector``). :class:`DropoutNet` is the
FourierNet with MC dropout, the baseline users know for a network's uncertainty; it and the
paper's BayesNet are :class:`StochasticNet` s, whose passes draw noise from one generator.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


class SirenLayer(nn.Module):
    """``sin(scale * (W x + b))`` with SIREN's first-layer initialisation of W."""

    def __init__(self, in_features: int, out_features: int, scale: float):
        super().__init__()
        self.linear = nn.Linear(in_features, out_features)
        self.scale = scale
        bound = math.sqrt(6 / out_features)
        with torch.no_grad():
            self.linear.weight.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # scale * (W x + b) with the scale folded into the (tiny) weights: the same function and
        # gradients, without two passes over the (points x width) activations.
        return torch.sin(F.linear(x, self.linear.weight * self.scale, self.linear.bias * self.scale))


class FourierNet(nn.Module):
    """DiNNO's FourierNet: shape [2, h1, ..., 1]; h1 is the sine layer, the rest ReLU, sigmoid out.
    ``hidden_layer(in, out)`` makes the hidden layers (the Bayesian network swaps in its own)."""

    def __init__(self, shape: list[int], scale: float, bounds: tuple[float, float, float, float],
                 hidden_layer: Callable[[int, int], nn.Module] = nn.Linear):
        super().__init__()
        self.shape = list(shape)
        self.scale = scale
        x0, y0, x1, y1 = bounds
        self.register_buffer("centre", torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2], dtype=torch.float32))
        layers: list[nn.Module] = [SirenLayer(shape[0], shape[1], scale)]
        for a, b in zip(shape[1:-2], shape[2:-1]):
            layers += [hidden_layer(a, b), nn.ReLU()]
        layers += [nn.Linear(shape[-2], shape[-1])]
        self.seq = nn.Sequential(*layers)

    def logits(self, xy: torch.Tensor) -> torch.Tensor:
        """Pre-sigmoid outputs (N,) for points ``xy`` (N, 2) in metres."""
        return self.seq(xy - self.centre).squeeze(-1)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Occupancy probabilities (N,) for points ``xy`` (N, 2) in metres."""
        return torch.sigmoid(self.logits(xy))


class NoiseSource(nn.Module):
    """A layer whose forward pass draws noise, from its ``generator`` (None: torch's global RNG)."""

    generator: torch.Generator | None = None

    def _draw(self, like: torch.Tensor, fn: Callable = torch.randn) -> torch.Tensor:
        """Noise shaped like ``like`` (``fn`` torch.randn or torch.rand), on its device."""
        if self.generator is None:
            return fn(like.shape, dtype=like.dtype, device=like.device)
        return fn(like.shape, generator=self.generator, device=self.generator.device).to(like.device, like.dtype)


class StochasticNet(FourierNet):
    """A FourierNet whose passes differ (weight draws, dropout masks): its prediction is the
    mean of several passes and their spread is its uncertainty. Every noise source of the
    network draws from one generator, set by :meth:`use_generator` or, for a block, :meth:`noise`."""

    def noise_sources(self) -> list[NoiseSource]:
        return [m for m in self.modules() if isinstance(m, NoiseSource)]

    def use_generator(self, generator: torch.Generator | None) -> None:
        """Draw every layer's noise from ``generator`` (None: torch's global RNG)."""
        for layer in self.noise_sources():
            layer.generator = generator

    @contextlib.contextmanager
    def noise(self, seed: int):
        """Within the block, draw noise from a fresh generator seeded ``seed`` (evaluation never
        disturbs the noise stream that training draws from)."""
        saved = [layer.generator for layer in self.noise_sources()]
        self.use_generator(torch.Generator(device=self.centre.device).manual_seed(seed))
        try:
            yield self
        finally:
            for layer, gen in zip(self.noise_sources(), saved):
                layer.generator = gen


class MCDropout(NoiseSource):
    """Dropout that stays on when predicting (MC dropout, Gal and Ghahramani, "Dropout as a
    Bayesian Approximation", 2016): each pass zeroes each unit with probability ``p`` and
    scales the others by 1 / (1 - p)."""

    def __init__(self, p: float):
        super().__init__()
        if not 0 <= p < 1:
            raise ValueError(f"dropout probability must lie in [0, 1), got {p}")
        self.p = p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.p == 0:
            return x
        keep = 1.0 - self.p
        return x * (self._draw(x, torch.rand) < keep).to(x.dtype) / keep


class DropoutNet(StochasticNet):
    """DiNNO's FourierNet with MC dropout before every layer after the sine layer: the same
    parameters as the FourierNet (the same State), a mean and a spread from its passes."""

    def __init__(self, shape: list[int], scale: float, bounds: tuple[float, float, float, float], p: float = 0.1):
        super().__init__(shape, scale, bounds, hidden_layer=lambda a, b: nn.Sequential(MCDropout(p), nn.Linear(a, b)))
        self.seq[-1] = nn.Sequential(MCDropout(p), self.seq[-1])
        self.p = p


@torch.no_grad()
def flatten_into(tensors: list[torch.Tensor], out: np.ndarray) -> np.ndarray:
    """Write ``tensors`` (any device) one after another into the float32 vector ``out``, in one
    pass: a node's State goes straight into the buffer it is sent from."""
    flat = [t.detach().reshape(-1) for t in tensors]
    if sum(t.numel() for t in flat) != out.size:
        raise ValueError(f"{out.size} values to fill, the tensors have {sum(t.numel() for t in flat)}")
    dst = torch.from_numpy(out)
    if all(t.device.type == "cpu" and t.dtype == torch.float32 for t in flat):
        torch.cat(flat, out=dst)
    else:
        dst.copy_(torch.cat([t.to(torch.float32) for t in flat]))
    return out


@torch.no_grad()
def set_flat(model: nn.Module, flat: torch.Tensor) -> None:
    """Copy a flat vector into the model's parameters.

    Copies, unlike ``torch.nn.utils.vector_to_parameters``, which makes the parameters views of
    ``flat``: training would then write into the caller's array (a neighbour's State, say).
    """
    offset = 0
    for p in model.parameters():
        n = p.numel()
        p.copy_(flat[offset : offset + n].view_as(p))
        offset += n
    if offset != flat.numel():
        raise ValueError(f"flat vector has {flat.numel()} values, the model {offset} parameters")


def param_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@torch.no_grad()
def predict(model: FourierNet, points: np.ndarray, batch: int = 65536) -> np.ndarray:
    """Occupancy probabilities (N,) float32 of ``points`` (N, 2), in batches."""
    device = next(model.parameters()).device
    out = []
    for s in range(0, len(points), batch):
        xy = torch.as_tensor(points[s : s + batch], dtype=torch.float32, device=device)
        out.append(model(xy).cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0, dtype=np.float32)


def pick_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu; anything else as given."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)
