"""What one robot's learner of a run needs in memory, measured before the run starts.

``python -m swarmmap.services.learner.probe`` reads a run's config (JSON, on stdin) and the size of
the largest robot's data, imports what a learner imports, builds the run's network and node on as
many synthetic points, runs two of its rounds against as many neighbours' States as its graph gives
it, takes the validation loss on a set of the run's size, evaluates a map of the run's cells with
the learner's Monte-Carlo passes, and prints (JSON) the
peak of its anonymous memory. ``up --budget`` adds what the probe leaves out
(:func:`swarmmap.services.up.budget.needs`) and refuses a run whose robots cannot hold it, naming
the smallest budget that would."""

from __future__ import annotations

import json
import sys


def status_kib() -> dict[str, int]:
    """This process's memory figures from /proc/self/status (kB)."""
    with open("/proc/self/status") as f:
        return {k: int(v.split()[0]) for k, _, v in (line.partition(":") for line in f) if v.strip().endswith("kB")}


def peak_anon_bytes() -> int:
    """The peak of this process's anonymous memory: its peak resident memory (``VmHWM``, kept by
    the kernel, so no brief peak is missed) less the library pages and shared memory it holds now
    (once mapped, they stay)."""
    s = status_kib()
    return (s["VmHWM"] - s.get("RssFile", 0) - s.get("RssShmem", 0)) * 1024


def measure(doc: dict) -> dict:
    from swarmmap.shared.run.limits import return_big_blocks

    return_big_blocks()  # (as a learner on a budget does)
    import numpy as np
    import torch

    import swarmmap.services.learner.service  # noqa: F401 - what a learner process imports
    from swarmmap.services.learner.metrics import validation_bce
    from swarmmap.services.learner.registry import node_for
    from swarmmap.shared.learning.bnn import predict_mean_std
    from swarmmap.shared.learning.networks import build_network
    from swarmmap.shared.run.config import RunConfig

    cfg = RunConfig.model_validate(doc["config"])
    torch.set_num_threads(1)
    w, h = doc["size_m"]
    bounds = (0.0, 0.0, float(w), float(h))
    rng = np.random.default_rng(0)
    n = max(int(doc["points"]), 1)
    points = (rng.random((n, 2)) * [w, h]).astype(np.float32)
    labels = (rng.random(n) < 0.3).astype(np.float32)
    model = build_network(cfg.network(), bounds, cfg.seed)
    degree = max(int(doc["degree"]), 0)
    graph = {0: set(range(1, degree + 1)), **{j: {0} for j in range(1, degree + 1)}}
    node = node_for(cfg.learner, model, points, labels, cfg.seed, bounds=bounds, graph=graph, robot=0)
    val = int(doc.get("val_points", 0))
    val_x = torch.from_numpy((rng.random((val, 2)) * [w, h]).astype(np.float32))
    val_y = torch.from_numpy((rng.random(val) < 0.3).astype(np.float32))
    state = node.state()
    peers = {j: state.copy() for j in range(1, degree + 1)}
    for k in range(2):  # (as a learner: a round's validation loss, then its update)
        validation_bce(model, val_x, val_y)
        state = node.update(k, state, peers)
    cells = max(int(doc["cells"]), 1)
    side = int(np.ceil(np.sqrt(cells)))
    grid = np.stack(np.meshgrid(np.linspace(0, w, side), np.linspace(0, h, side)), -1).reshape(-1, 2)[:cells]
    predict_mean_std(model, grid.astype(np.float32), samples=cfg.learner.mc_samples)
    return {"peak_anon_bytes": peak_anon_bytes(), "state_bytes": int(state.nbytes)}


if __name__ == "__main__":
    print(json.dumps(measure(json.load(sys.stdin))), flush=True)
