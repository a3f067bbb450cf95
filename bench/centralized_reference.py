"""Centralized reference for a finished run: one model trained on ALL robots' points.

    python bench/centralized_reference.py RUN_DIR

Reads RUN_DIR/config.yaml, RUN_DIR/data/robot-*.npz and RUN_DIR/groundtruth.npz, trains one
FourierNet of the run's shape for the same number of optimizer steps as each learner took
(rounds x primal_iterations, same batch size, optimizer and learning-rate schedule, a fresh
optimizer each round as DiNNO does) on the union of the robots' points, and prints its
validation BCE beside the learners' final val_bce from RUN_DIR/summary.json.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from swarmmap.services.learner.metrics import validation_bce
from swarmmap.services.learner.node import lr_schedule
from swarmmap.services.learner.optim import make_optimizer
from swarmmap.shared.learning.networks import build_model
from swarmmap.shared.run.config import RunConfig


def main(run_dir: Path) -> None:
    cfg = RunConfig.model_validate(yaml.safe_load((run_dir / "config.yaml").read_text()))
    s = cfg.learner
    files = sorted((run_dir / "data").glob("robot-*.npz"))
    if not files:
        raise SystemExit(f"{run_dir}/data holds no robot-*.npz: was the run finished?")
    data = [np.load(f) for f in files]
    x = torch.from_numpy(np.concatenate([d["points"] for d in data]))
    y = torch.from_numpy(np.concatenate([d["labels"] for d in data]))
    gt = np.load(run_dir / "groundtruth.npz")
    vx, vy = torch.from_numpy(gt["val_points"]), torch.from_numpy(gt["val_labels"])
    h, w = gt["grid"].shape
    x0, y0 = gt["origin"]
    res = float(gt["resolution"])
    torch.set_num_threads(1)
    model = build_model(s.model_shape, s.siren_scale, (x0, y0, x0 + w * res, y0 + h * res), cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    lrs = lr_schedule(s.lr_schedule, s.lr_start, s.lr_finish, s.rounds)
    t0 = time.perf_counter()
    for k in range(s.rounds):
        opt = make_optimizer(s.optimizer, model.parameters(), float(lrs[k]))
        for _ in range(s.primal_iterations):
            idx = torch.randint(0, len(x), (min(s.batch_size, len(x)),), generator=gen)
            loss = F.binary_cross_entropy_with_logits(model.logits(x[idx]), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    elapsed = time.perf_counter() - t0
    central = validation_bce(model, vx, vy)
    summary = json.loads((run_dir / "summary.json").read_text())
    finals = {r: v["final_val_bce"] for r, v in summary["learners"].items()}
    print(f"run {cfg.run_id}: {len(files)} robots, {len(x)} points, {s.rounds} rounds x {s.primal_iterations} steps")
    print(f"centralized val_bce: {central:.4f}  ({elapsed:.1f} s on one thread)")
    print("DiNNO learners' final val_bce: " + ", ".join(f"robot {r} {v:.4f}" for r, v in sorted(finals.items())))
    print(f"DiNNO mean final val_bce: {np.mean(list(finals.values())):.4f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    main(Path(sys.argv[1]))
