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

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from swarmmap.shared.learning.models import DropoutNet, MCDropout, NoiseSource, StochasticNet


def gaussian_kl(mu0: torch.Tensor, sigma0: torch.Tensor, mu1: torch.Tensor | float, sigma1: torch.Tensor | float) -> torch.Tensor:
    """Elementwise KL(N(mu0, sigma0^2) || N(mu1, sigma1^2)), the paper's equation 6."""
    sigma1 = torch.as_tensor(sigma1, dtype=sigma0.dtype, device=sigma0.device)
    mu1 = torch.as_tensor(mu1, dtype=mu0.dtype, device=mu0.device)
    return 0.5 * (torch.log(sigma1**2 / sigma0**2) + (sigma0**2 + (mu0 - mu1) ** 2) / sigma1**2 - 1.0)


class BayesLinear(NoiseSource):
    """A linear layer with Gaussian weights and biases: (mu, rho) each, sigma = softplus(rho).

    ``local_reparam`` (Kingma et al., "Variational Dropout and the Local Reparameterization
    Trick", 2015): instead of one weight draw for the batch, draw each example's outputs from
    the Gaussian they follow under the posterior, N(x mu_W + mu_b, x^2 sigma_W^2 + sigma_b^2):
    the same distribution for every example, drawn independently per example, so the
    gradient's variance falls with the batch. It changes only the training passes; the maps
    draw whole weights either way."""

    def __init__(self, in_features: int, out_features: int, prior_sigma: float = 0.1, rho_init: float = -5.0,
                 local_reparam: bool = False):
        super().__init__()
        self.prior_sigma = prior_sigma
        self.local_reparam = local_reparam
        self.weight_mu = nn.Parameter(torch.empty(out_features, in_features))
        self.weight_rho = nn.Parameter(torch.full((out_features, in_features), rho_init))
        self.bias_mu = nn.Parameter(torch.empty(out_features))
        self.bias_rho = nn.Parameter(torch.full((out_features,), rho_init))
        bound = 1 / math.sqrt(in_features)  # nn.Linear's initialisation of the means
        with torch.no_grad():
            nn.init.kaiming_uniform_(self.weight_mu, a=math.sqrt(5))
            self.bias_mu.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        sw, sb = F.softplus(self.weight_rho), F.softplus(self.bias_rho)
        if self.local_reparam:
            mean = F.linear(x, self.weight_mu, self.bias_mu)
            var = F.linear(x * x, sw * sw, sb * sb)
            return mean + var.clamp_min(1e-16).sqrt() * self._draw(mean)
        return F.linear(x, self.weight_mu + sw * self._draw(self.weight_mu), self.bias_mu + sb * self._draw(self.bias_mu))

    def kl(self) -> torch.Tensor:
        """Summed KL of the layer's weights and biases to the prior N(0, prior_sigma^2)."""
        return (gaussian_kl(self.weight_mu, F.softplus(self.weight_rho), 0.0, self.prior_sigma).sum()
                + gaussian_kl(self.bias_mu, F.softplus(self.bias_rho), 0.0, self.prior_sigma).sum())

    def n_params(self) -> int:
        return self.weight_mu.numel() + self.bias_mu.numel()


class BayesNet(StochasticNet):
    """The paper's BNN: (x, y) -> SIREN (h1, sine) -> Bayesian linear layers (ReLU) -> linear (1, sigmoid)."""

    def __init__(self, shape: list[int], scale: float, bounds: tuple[float, float, float, float],
                 prior_sigma: float = 0.1, rho_init: float = -5.0, local_reparam: bool = False):
        super().__init__(shape, scale, bounds,
                         hidden_layer=lambda a, b: BayesLinear(a, b, prior_sigma, rho_init, local_reparam))

    def bayes_layers(self) -> list[BayesLinear]:
        return [m for m in self.seq if isinstance(m, BayesLinear)]

    def kl(self) -> torch.Tensor:
        """Mean KL per Bayesian parameter to the prior (the ``kl_loss`` of equation 7)."""
        layers = self.bayes_layers()
        if not layers:
            return torch.zeros(())
        return sum(layer.kl() for layer in layers) / sum(layer.n_params() for layer in layers)


def is_rho(name: str) -> bool:
    """Algorithm 2's split: rho-parameters are the ones named ``*_rho``; everything else is mu."""
    return name.endswith("_rho")


def fast_bf16(device: torch.device | str) -> bool:
    """Whether ``device`` multiplies bfloat16 matrices in hardware (a CUDA GPU with bf16, or a CPU
    with AMX or AVX512-BF16); elsewhere bf16 is emulated and slower than fp32."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device.type != "cpu":
        return False
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "amx_bf16" in flags or "avx512_bf16" in flags


def sample_weights(layer: BayesLinear, samples: int, generator: torch.Generator | None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """``samples`` draws of the layer's weights, transposed for ``x @ W`` (S, in, out), and of its
    biases (S, 1, out), by the same reparameterisation as :meth:`BayesLinear.forward`."""
    def draw(mu: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
        shape = (samples, *mu.shape)
        if generator is None:
            eps = torch.randn(shape, device=mu.device)
        else:
            eps = torch.randn(shape, generator=generator, device=generator.device).to(mu.device)
        return mu + F.softplus(rho) * eps

    w = draw(layer.weight_mu, layer.weight_rho).transpose(1, 2).contiguous()
    b = draw(layer.bias_mu, layer.bias_rho).unsqueeze(1)
    return w, b


class MapPlan:
    """The S-pass evaluation of a :class:`BayesNet`, laid out for batched matrix products.

    The layers before the first Bayesian one (the SIREN layer) are deterministic: they run once
    per point, not once per pass. Each Bayesian layer's S weight draws are sampled once for the
    whole map and applied to all passes together with one batched product (``baddbmm``) per
    chunk of points, into two reused activation buffers; ReLUs run in place. A chunk of
    ``points_per_chunk`` points keeps the (S, chunk, width) activations inside the CPU's caches.
    """

    def __init__(self, model: BayesNet, samples: int, generator: torch.Generator | None, dtype: torch.dtype):
        layers = list(model.seq)
        first = next(i for i, m in enumerate(layers) if isinstance(m, BayesLinear))
        self.model = model
        self.head = nn.Sequential(*layers[:first])
        self.samples = samples
        self.dtype = dtype
        self.steps: list[tuple[str, object]] = []
        for m in layers[first:]:
            if isinstance(m, BayesLinear):
                w, b = sample_weights(m, samples, generator)
                self.steps.append(("bayes", (w.to(dtype), b.to(dtype))))
            elif isinstance(m, nn.ReLU):
                self.steps.append(("relu", None))
            elif isinstance(m, nn.Linear):
                self.steps.append(("linear", (m.weight.t().to(dtype), None if m.bias is None else m.bias.to(dtype))))
            else:
                self.steps.append(("module", m))
        self.widths = [arg[0].shape[-1] for kind, arg in self.steps if kind == "bayes"]

    def logits(self, xy: torch.Tensor) -> torch.Tensor:
        """Pre-sigmoid outputs (S, N) of every pass for points ``xy`` (N, 2)."""
        h = self.head(xy - self.model.centre).to(self.dtype)  # (N, h1), shared by every pass
        n, widest = h.shape[0], max(self.widths)
        bufs = [torch.empty(self.samples * n * widest, dtype=self.dtype, device=h.device) for _ in range(2)]
        which = 0
        for kind, arg in self.steps:
            if kind == "bayes":
                w, b = arg
                out = bufs[which][: self.samples * n * w.shape[-1]].view(self.samples, n, w.shape[-1])
                which ^= 1
                if h.dim() == 2:  # the first Bayesian layer: one input for every pass
                    h = h.unsqueeze(0).expand(self.samples, -1, -1)
                torch.baddbmm(b, h, w, out=out)
                h = out
            elif kind == "relu":
                h = h.relu_()
            elif kind == "linear":
                w, b = arg
                h = torch.matmul(h, w) if b is None else torch.matmul(h, w) + b
            else:
                h = arg(h)
        return h.squeeze(-1).float()


@torch.no_grad()
def predict_mean_std(model: nn.Module, points: np.ndarray, samples: int = 50, batch: int = 8192,
                     seed: int = 0, points_per_chunk: int | None = None, sample_chunk: int = 64,
                     dtype: torch.dtype = torch.float32, std_of: str = "probability") -> tuple[np.ndarray, np.ndarray]:
    """Mean occupancy and its standard deviation (N,) over ``samples`` stochastic passes
    (float32 numpy arrays). A deterministic model gives its output and zero spread.
    ``std_of="logit"``: the spread of the passes' pre-sigmoid outputs instead (the predictive
    variance in logit space, which a sigmoid squashes near 0 and 1).

    A BNN's weights are drawn once per pass for the whole map, from a generator seeded
    ``seed``, so the result does not depend on how the points are chunked. The passes run
    together in groups of ``sample_chunk`` (memory for their weights stays bounded at any
    ``samples``) over chunks of points (``points_per_chunk``, by default sized so one group's
    activations take about 8 MB; ``batch`` caps it). ``dtype=torch.bfloat16`` runs the
    products in bf16 where :func:`fast_bf16` says the hardware has it; means and spreads are
    accumulated in float64. An MC-dropout network (:class:`DropoutPlan`) draws one mask per
    pass and layer for the whole map, the same way."""
    if std_of not in ("probability", "logit"):
        raise ValueError(f"std_of must be probability or logit, got {std_of!r}")
    device = next(model.parameters()).device
    bayes = isinstance(model, BayesNet) and bool(model.bayes_layers())
    if not bayes and not isinstance(model, DropoutNet):
        out = _predict_deterministic(model, points, batch, device)
        return out, np.zeros_like(out)
    generator = torch.Generator(device=device).manual_seed(seed)
    total = torch.zeros(len(points), dtype=torch.float64, device=device)
    squares = torch.zeros(len(points), dtype=torch.float64, device=device)  # of what the std is taken of
    logit_sum = torch.zeros(len(points), dtype=torch.float64, device=device) if std_of == "logit" else None
    done = 0
    while done < samples:
        group = min(sample_chunk, samples - done)
        plan = MapPlan(model, group, generator, dtype) if bayes else DropoutPlan(model, group, generator)
        chunk = points_per_chunk or max(16, min(batch, (8 << 20) // (4 * group * max(plan.widths))))
        for s in range(0, len(points), chunk):
            xy = torch.as_tensor(points[s : s + chunk], dtype=torch.float32, device=device)
            z = plan.logits(xy)
            p = torch.sigmoid(z).double()
            total[s : s + chunk] += p.sum(0)
            if logit_sum is None:
                squares[s : s + chunk] += (p * p).sum(0)
            else:
                z = z.double()
                logit_sum[s : s + chunk] += z.sum(0)
                squares[s : s + chunk] += (z * z).sum(0)
        done += group
    mean = total / samples
    centre = mean if logit_sum is None else logit_sum / samples
    std = (squares / samples - centre * centre).clamp_min(0).sqrt()
    return mean.float().cpu().numpy(), std.float().cpu().numpy()


class DropoutPlan:
    """The S-pass evaluation of a :class:`DropoutNet`, laid out like :class:`MapPlan`: each pass
    draws one mask per dropout layer for the whole map (a sub-network, as a BNN's pass draws
    its weights once), so the result does not depend on how the points are chunked, and the
    sine layer runs once per point. Each point's passes follow the distribution of dropout's
    passes in training, where masks are drawn per example."""

    def __init__(self, model: DropoutNet, samples: int, generator: torch.Generator | None):
        self.model, self.samples = model, samples
        self.layers = [x for m in model.seq for x in (m if isinstance(m, nn.Sequential) else [m])]
        self.masks = {}
        for i, m in enumerate(self.layers):
            if isinstance(m, MCDropout) and m.p > 0:
                width = next(x for x in self.layers[i + 1 :] if isinstance(x, nn.Linear)).in_features
                draw = torch.rand((samples, 1, width), generator=generator, device=model.centre.device)
                self.masks[i] = (draw < 1.0 - m.p).to(torch.float32) / (1.0 - m.p)
        self.widths = list(model.shape[1:-1])

    def logits(self, xy: torch.Tensor) -> torch.Tensor:
        """Pre-sigmoid outputs (S, N) of every pass for points ``xy`` (N, 2)."""
        h = self.layers[0](xy - self.model.centre).unsqueeze(0)  # the sine layer: (1, N, h1), shared by every pass
        for i, m in enumerate(self.layers[1:], start=1):
            if isinstance(m, MCDropout):
                if i in self.masks:
                    h = h * self.masks[i]
            else:
                h = m(h)
        return h.expand(self.samples, -1, -1).squeeze(-1).float()


def _predict_deterministic(model: nn.Module, points: np.ndarray, batch: int, device: torch.device) -> np.ndarray:
    out = []
    for s in range(0, len(points), batch):
        xy = torch.as_tensor(points[s : s + batch], dtype=torch.float32, device=device)
        out.append(model(xy).float().cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0, np.float32)


def sampled_logits(model: BayesNet, xy: torch.Tensor, samples: int, generator: torch.Generator | None) -> torch.Tensor:
    """Pre-sigmoid outputs (S, N) of ``samples`` weight draws at points ``xy`` (N, 2), with their
    gradients (training's counterpart of :class:`MapPlan`: the same draws, no reused buffers)."""
    layers = list(model.seq)
    first = next(i for i, m in enumerate(layers) if isinstance(m, BayesLinear))
    h = nn.Sequential(*layers[:first])(xy - model.centre).unsqueeze(0).expand(samples, -1, -1)
    for m in layers[first:]:
        if isinstance(m, BayesLinear):
            w, b = sample_weights(m, samples, generator)
            h = torch.baddbmm(b, h, w)
        else:
            h = m(h)
    return h.squeeze(-1)


def function_prior_kl(logits: torch.Tensor, prior_std: float) -> torch.Tensor:
    """A noise-contrastive prior's term (Hafner et al., "Noise Contrastive Priors for Functional
    Uncertainty", 2019), for points away from the data: KL(N(m, v) || N(0, prior_std^2)) of
    the Gaussian fitted to each point's logits over the weight draws (rows of ``logits``),
    mean over the points. It is small where the network's draws disagree as much as the prior
    says an unseen place should (occupancy anywhere between free and occupied), large where
    the network is sure of a place it has no data of."""
    m = logits.mean(0)
    v = logits.var(0) + 1e-6
    s2 = prior_std * prior_std
    return (0.5 * (torch.log(s2 / v) + (v + m * m) / s2 - 1.0)).mean()
