"""The learner's optimizers: Adam, AdamW and SGD, step for step as torch's own on a CPU (their
single-tensor code: the same operations in the same order, so the same bits), without
``torch.optim``.

Why not ``torch.optim``: every torch optimizer imports ``torch._dynamo`` (and sympy with it) on its
first ``__init__`` and ``step``, only to switch the compiler off around them: 67 MB of resident memory
and about 1.5 s of one core in every learner process, which never compiles. On a robot's budget
(``up.budget``) that is a seventh of 512 MiB. The state dicts have torch's layout, so a checkpoint
written by either loads into the other."""

from __future__ import annotations

from collections.abc import Iterable

import torch


class Optimizer:
    """The part of ``torch.optim.Optimizer`` the learner uses: ``param_groups`` (one, its ``lr``
    settable), :meth:`zero_grad`, :meth:`step`, :meth:`state_dict`, :meth:`load_state_dict`."""

    def __init__(self, params: Iterable[torch.Tensor], defaults: dict):
        self.params = list(params)
        self.param_groups = [{**defaults, "params": self.params}]
        self.state: dict[int, dict[str, torch.Tensor]] = {}

    @property
    def group(self) -> dict:
        return self.param_groups[0]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def state_dict(self) -> dict:
        return {"state": {i: dict(s) for i, s in self.state.items()},
                "param_groups": [{**{k: v for k, v in self.group.items() if k != "params"},
                                  "params": list(range(len(self.params)))}]}

    def load_state_dict(self, doc: dict) -> None:
        groups = doc["param_groups"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(self.params):
            raise ValueError(f"an optimizer state of {[len(g['params']) for g in groups]} parameters for one group of "
                             f"{len(self.params)}")
        self.group.update({k: v for k, v in groups[0].items() if k != "params"})
        self.state = {int(i): {k: v.to(self.params[int(i)].device) if k != "step" else v.clone() for k, v in s.items()}
                      for i, s in doc["state"].items()}


class Adam(Optimizer):
    """torch's Adam (AdamW with ``weight_decay``: decoupled, as ``torch.optim.AdamW``), no amsgrad."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8, weight_decay: float = 0.0, decoupled_weight_decay: bool = False):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps, "weight_decay": weight_decay, "amsgrad": False,
                                  "maximize": False, "foreach": None, "capturable": False, "differentiable": False,
                                  "fused": None, "decoupled_weight_decay": decoupled_weight_decay})

    @torch.no_grad()
    def step(self) -> None:
        g = self.group
        lr, (beta1, beta2), eps, decay = g["lr"], g["betas"], g["eps"], g["weight_decay"]
        for i, param in enumerate(self.params):
            grad = param.grad
            if grad is None:
                continue
            s = self.state.get(i)
            if s is None:
                s = self.state[i] = {"step": torch.tensor(0.0, dtype=torch.float32),
                                     "exp_avg": torch.zeros_like(param, memory_format=torch.preserve_format),
                                     "exp_avg_sq": torch.zeros_like(param, memory_format=torch.preserve_format)}
            s["step"] += 1
            if decay != 0:
                if g["decoupled_weight_decay"]:
                    param.mul_(1 - lr * decay)
                else:
                    grad = grad.add(param, alpha=decay)
            s["exp_avg"].lerp_(grad, 1 - beta1)
            s["exp_avg_sq"].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step = s["step"].item()
            bias_correction1 = 1 - beta1**step
            bias_correction2 = 1 - beta2**step
            step_size = lr / bias_correction1
            denom = (s["exp_avg_sq"].sqrt() / bias_correction2**0.5).add_(eps)
            param.addcdiv_(s["exp_avg"], denom, value=-step_size)


class SGD(Optimizer):
    """torch's SGD without momentum or weight decay."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float = 1e-3):
        super().__init__(params, {"lr": lr, "momentum": 0, "dampening": 0, "weight_decay": 0, "nesterov": False,
                                  "maximize": False, "foreach": None, "differentiable": False, "fused": None})

    @torch.no_grad()
    def step(self) -> None:
        lr = self.group["lr"]
        for param in self.params:
            if param.grad is not None:
                param.add_(param.grad, alpha=-lr)


def make_optimizer(kind: str, params, lr: float) -> Optimizer:
    """The optimizer of ``kind`` (adam, adamw, sgd) over ``params``, each with torch's defaults."""
    if kind == "adam":
        return Adam(params, lr=lr)
    if kind == "adamw":
        return Adam(params, lr=lr, weight_decay=1e-2, decoupled_weight_decay=True)
    if kind == "sgd":
        return SGD(params, lr=lr)
    raise ValueError(f"unknown optimizer {kind!r}; allowed: adam, adamw, sgd")
