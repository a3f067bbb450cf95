"""The learner's optimizers against torch's: the same bits step for step, state dicts that load
either way, and a learner process that never imports torch's compiler."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from swarmmap.services.learner.optim import make_optimizer


def trained(optimizer, params, rounds: int = 6) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(64, 5, generator=gen)
    for k in range(rounds):
        for group in optimizer.param_groups:
            group["lr"] = 0.05 / (k + 1)  # (the learner's schedule sets it each round)
        optimizer.zero_grad()
        w, b = params
        loss = torch.nn.functional.softplus(x @ w + b).pow(2).mean() + 0.1 * w.abs().sum()
        loss.backward()
        optimizer.step()
    return [p.detach().clone() for p in params]


def fresh() -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(1)
    return [torch.randn(5, 3, generator=gen).requires_grad_(), torch.randn(3, generator=gen).requires_grad_()]


TORCH = {"adam": lambda p: torch.optim.Adam(p, lr=0.05), "adamw": lambda p: torch.optim.AdamW(p, lr=0.05),
         "sgd": lambda p: torch.optim.SGD(p, lr=0.05)}


@pytest.mark.parametrize("kind", ["adam", "adamw", "sgd"])
def test_each_optimizer_gives_torchs_bits(kind):
    ours, theirs = fresh(), fresh()
    got = trained(make_optimizer(kind, ours, 0.05), ours)
    want = trained(TORCH[kind](theirs), theirs)
    for a, b in zip(got, want):
        assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ["adam", "adamw"])
def test_a_state_dict_loads_into_torchs_optimizer_and_back(kind):
    """A checkpoint written with either goes on with the other, to the same bits."""
    ours, theirs = fresh(), fresh()
    ours_opt, theirs_opt = make_optimizer(kind, ours, 0.05), TORCH[kind](theirs)
    trained(ours_opt, ours, rounds=3)
    trained(theirs_opt, theirs, rounds=3)
    swapped_ours, swapped_theirs = [p.detach().clone().requires_grad_() for p in ours], \
        [p.detach().clone().requires_grad_() for p in theirs]
    a, b = TORCH[kind](swapped_ours), make_optimizer(kind, swapped_theirs, 0.05)
    a.load_state_dict(ours_opt.state_dict())
    b.load_state_dict(theirs_opt.state_dict())
    for x, y in zip(trained(a, swapped_ours, rounds=3), trained(b, swapped_theirs, rounds=3)):
        assert torch.equal(x, y)
    with pytest.raises(ValueError, match="parameters for one group"):
        make_optimizer(kind, fresh()[:1], 0.05).load_state_dict(ours_opt.state_dict())


def test_a_learner_process_never_imports_torchs_compiler_or_the_world():
    """torch's optimizers import torch._dynamo and sympy (67 MB); the world's geometry (shapely,
    pybullet, trimesh) and scipy belong to other services."""
    code = ("import sys; import swarmmap.services.cli, swarmmap.services.learner.service as s;"
            "from swarmmap.services.learner.node import warm_up; warm_up('adam');"
            "print(sorted(m for m in ('torch._dynamo', 'sympy', 'shapely', 'pybullet', 'trimesh', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
