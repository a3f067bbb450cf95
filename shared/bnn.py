"""The paper's Bayesian neural network (its Section 5) and its uncertainty maps.

A :class:`BayesLinear` layer holds mu and rho for its weights and biases; sigma =
softplus(rho) (the paper's equations 3 and 4); each forward pass samples weights by
reparameterisation, w = mu + sigma * eps. :meth:`BayesLinear.kl` is the closed-form KL
divergence of q = N(mu, sigma^2) to the Gaussian prior N(0, prior_sigma^2) (equation 6),
summed over the layer. :class:`BayesNet` is the paper's network: a SIREN layer, Bayesian
ReLU layers and a deterministic linear output with a sigmoid; the loss is
BCE + kl_weight * KL (equation 7), with KL the mean over every Bayesian parameter (torchbnn's
``BKLLoss`` convention, which makes kl_weight independent of the network's size).
:func:`predict_mean_std` draws S forward passes per point (S = 50 in the paper).
Every rho parameter's name ends in ``_rho``: that is how Algorithm 2 splits the parameters.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from swarmmap.shared.models import FourierNet


def gaussian_kl(mu0: torch.Tensor, sigma0: torch.Tensor, mu1: torch.Tensor | float, sigma1: torch.Tensor | float) -> torch.Tensor:
    """Elementwise KL(N(mu0, sigma0^2) || N(mu1, sigma1^2)), the paper's equation 6."""
    sigma1 = torch.as_tensor(sigma1, dtype=sigma0.dtype, device=sigma0.device)
    mu1 = torch.as_tensor(mu1, dtype=mu0.dtype, device=mu0.device)
    return 0.5 * (torch.log(sigma1**2 / sigma0**2) + (sigma0**2 + (mu0 - mu1) ** 2) / sigma1**2 - 1.0)


class BayesLinear(nn.Module):
    """A linear layer with Gaussian weights and biases: (mu, rho) each, sigma = softplus(rho)."""

    def __init__(self, in_features: int, out_features: int, prior_sigma: float = 0.1, rho_init: float = -5.0):
        super().__init__()
        self.prior_sigma = prior_sigma
        self.generator: torch.Generator | None = None  # per-node noise, so threads never share an RNG
        self.weight_mu = nn.Parameter(torch.empty(out_features, in_features))
        self.weight_rho = nn.Parameter(torch.full((out_features, in_features), rho_init))
        self.bias_mu = nn.Parameter(torch.empty(out_features))
        self.bias_rho = nn.Parameter(torch.full((out_features,), rho_init))
        bound = 1 / math.sqrt(in_features)  # nn.Linear's initialisation of the means
        with torch.no_grad():
            nn.init.kaiming_uniform_(self.weight_mu, a=math.sqrt(5))
            self.bias_mu.uniform_(-bound, bound)

    def _noise(self, like: torch.Tensor) -> torch.Tensor:
        if self.generator is None:
            return torch.randn_like(like)
        return torch.randn(like.shape, generator=self.generator, device=self.generator.device).to(like.device)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = self.weight_mu + F.softplus(self.weight_rho) * self._noise(self.weight_mu)
        b = self.bias_mu + F.softplus(self.bias_rho) * self._noise(self.bias_mu)
        return F.linear(x, w, b)

    def kl(self) -> torch.Tensor:
        """Summed KL of the layer's weights and biases to the prior N(0, prior_sigma^2)."""
        return (gaussian_kl(self.weight_mu, F.softplus(self.weight_rho), 0.0, self.prior_sigma).sum()
                + gaussian_kl(self.bias_mu, F.softplus(self.bias_rho), 0.0, self.prior_sigma).sum())

    def n_params(self) -> int:
        return self.weight_mu.numel() + self.bias_mu.numel()


class BayesNet(FourierNet):
    """The paper's BNN: (x, y) -> SIREN (h1, sine) -> Bayesian linear layers (ReLU) -> linear (1, sigmoid)."""

    def __init__(self, shape: list[int], scale: float, bounds: tuple[float, float, float, float],
                 prior_sigma: float = 0.1, rho_init: float = -5.0):
        super().__init__(shape, scale, bounds, hidden_layer=lambda a, b: BayesLinear(a, b, prior_sigma, rho_init))

    def bayes_layers(self) -> list[BayesLinear]:
        return [m for m in self.seq if isinstance(m, BayesLinear)]

    def use_generator(self, generator: torch.Generator | None) -> None:
        """Draw every layer's weight noise from ``generator`` (None: torch's global RNG)."""
        for layer in self.bayes_layers():
            layer.generator = generator

    @contextlib.contextmanager
    def noise(self, seed: int):
        """Within the block, draw weight noise from a fresh generator seeded ``seed`` (evaluation
        never disturbs the noise stream that training draws from)."""
        saved = [layer.generator for layer in self.bayes_layers()]
        device = self.centre.device
        self.use_generator(torch.Generator(device=device).manual_seed(seed))
        try:
            yield self
        finally:
            for layer, gen in zip(self.bayes_layers(), saved):
                layer.generator = gen

    def kl(self) -> torch.Tensor:
        """Mean KL per Bayesian parameter to the prior (the ``kl_loss`` of equation 7)."""
        layers = self.bayes_layers()
        if not layers:
            return torch.zeros(())
        return sum(layer.kl() for layer in layers) / sum(layer.n_params() for layer in layers)


def is_rho(name: str) -> bool:
    """Algorithm 2's split: rho-parameters are the ones named ``*_rho``; everything else is mu."""
    return name.endswith("_rho")


@torch.no_grad()
def predict_mean_std(model: nn.Module, points: np.ndarray, samples: int = 50, batch: int = 8192,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (N,) of the occupancy over ``samples`` stochastic passes,
    computed in batches of points so that a whole map grid fits in memory. A deterministic
    model gives its output and zero spread."""
    device = next(model.parameters()).device
    bayesian = isinstance(model, BayesNet)
    with model.noise(seed) if bayesian else contextlib.nullcontext():
        means, stds = [], []
        for s in range(0, len(points), batch):
            xy = torch.as_tensor(points[s : s + batch], dtype=torch.float32, device=device)
            if bayesian:
                draws = torch.stack([model(xy) for _ in range(samples)])
                means.append(draws.mean(0).cpu().numpy())
                stds.append(draws.std(0, unbiased=False).cpu().numpy())
            else:
                out = model(xy).cpu().numpy()
                means.append(out)
                stds.append(np.zeros_like(out))
    if not means:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    return np.concatenate(means), np.concatenate(stds)
