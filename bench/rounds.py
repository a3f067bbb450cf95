"""Where a learner's round goes: compute, wait and send, against the FLOP floor of its steps.

    python bench/rounds.py [--preset dinno] [--rounds 40] [--robots N] [--floorplan F --waypoints W]
                           [--run-dir DIR] [--set section.field=value ...]

Runs ``swarmmap up`` (every learner its own process over Zenoh, no observer), then reads the
run's ``metrics.csv``: each learner reports its cumulative compute, wait and send seconds, so
the rounds between its first and last Metrics split into those three. The FLOP floor counts
the matrix products of the optimizer steps (forward, and backward at twice the forward: 3x
the forward FLOPs per point, ``primal_iterations`` steps of ``batch_size`` points a round) and
divides them by the fp32 matrix peak measured in this process: per learner at one thread
(each learner is given ``learner.torch_threads``) and for the whole team at every core.
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from procmem import growth, run_sampled  # noqa: E402


def peak(threads: int) -> float:
    """Best fp32 FLOP/s of square products at ``threads`` CPU threads."""
    saved = torch.get_num_threads()
    torch.set_num_threads(threads)
    best = 0.0
    for n in (1024, 2048):
        a, b = torch.randn(n, n), torch.randn(n, n)
        a @ b
        reps = max(3, int(1e11 / (2 * n**3)))
        t = time.perf_counter()
        for _ in range(reps):
            a @ b
        best = max(best, 2 * n**3 * reps / (time.perf_counter() - t))
    torch.set_num_threads(saved)
    return best


def step_flops(shape: list[int], batch: int, bayes: bool) -> float:
    """Matrix-product FLOPs of one optimizer step: forward and backward (3x forward) over the batch.
    A Bayesian layer's weight sampling is elementwise and not counted."""
    forward = sum(2 * a * b for a, b in zip(shape[:-1], shape[1:]))
    return 3 * forward * batch


def per_round(run_dir: Path, columns: dict[str, str], from_round: int = 0) -> dict[str, float]:
    """Seconds a round of each cumulative Metrics column (name -> column of metrics.csv): per
    learner, the change between its first Metrics at or after ``from_round`` and its last, over
    the rounds between them; the mean over learners."""
    per_robot: dict[str, list[dict]] = {}
    for r in csv.DictReader((run_dir / "metrics.csv").open()):
        if int(r["round"]) >= from_round:
            per_robot.setdefault(r["robot"], []).append(r)
    split: dict[str, list[float]] = {name: [] for name in columns}
    for mine in per_robot.values():
        mine.sort(key=lambda r: int(r["round"]))
        first, last = mine[0], mine[-1]
        n = int(last["round"]) - int(first["round"])
        if n > 0:
            for name, column in columns.items():
                split[name].append((float(last[column]) - float(first[column])) / n)
    return {name: sum(v) / len(v) for name, v in split.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="dinno")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--robots", type=int, default=None)
    ap.add_argument("--floorplan", default=None)
    ap.add_argument("--waypoints", default=None)
    ap.add_argument("--run-dir", type=Path, default=None, help="default: a temporary folder")
    ap.add_argument("--set", action="append", default=[], help="section.field=value, passed to swarmmap up")
    args = ap.parse_args()
    data = HERE.parent.parent / "shared" / "data" / "dinno-floorplan-32"
    if args.preset.startswith("dinno") and args.floorplan is None:
        if not data.exists():
            sys.exit(f"the dinno presets need DiNNO's plan: {data} is missing (or pass --floorplan and --waypoints)")
        args.floorplan, args.waypoints = str(data / "floor_img.png"), str(data / "tight_paths")
    run_dir = args.run_dir or Path(tempfile.mkdtemp(prefix="bench-rounds-")) / "run"
    cmd = [sys.executable, "-m", "swarmmap.services.cli", "up", "--preset", args.preset, "--rounds", str(args.rounds),
           "--no-observer", "--run-dir", str(run_dir)]
    if args.robots:
        cmd += ["--robots", str(args.robots)]
    if args.floorplan:
        cmd += ["--floorplan", args.floorplan]
    if args.waypoints:
        cmd += ["--waypoints", args.waypoints]
    for item in args.set:
        cmd += ["--set", item]
    status, err, wall, sampler = run_sampled(cmd)
    if status != 0:
        sys.exit(f"swarmmap up failed ({status}):\n{err[-3000:]}")
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    s = cfg["learner"]
    robots = cfg["robots"]
    mean = per_round(run_dir, {"round": "wall_time_s", "compute": "compute_s", "wait": "wait_s", "send": "send_s"})
    flops = s["primal_iterations"] * step_flops(s["model_shape"], s["batch_size"], s["model"] == "bnn")
    threads = s.get("torch_threads", 1)
    one, every = peak(threads), peak(torch.get_num_threads())
    floor_one = flops / one
    floor_team = robots * flops / every
    share = min(1.0, torch.get_num_threads() / (robots * threads))  # of a core, while every learner computes
    label = f"{args.preset} preset round, {robots} learners over Zenoh on {torch.get_num_threads()} cores"
    print(f"{label}: {mean['round']:.3f} s a round; per learner compute {mean['compute']:.3f} s, "
          f"wait {mean['wait']:.3f} s, send {mean['send']:.4f} s (run {wall:.0f} s, traversal included)")
    print(f"{label}, FLOP floor: team {floor_team:.3f} s a round at the {torch.get_num_threads()}-core fp32 peak "
          f"({every / 1e9:.0f} GFLOPS), round time {mean['round'] / floor_team:.1f}x the floor; one learner's steps "
          f"{floor_one:.3f} s at its {threads}-thread peak ({one / 1e9:.0f} GFLOPS), its compute "
          f"{mean['compute'] / floor_one:.1f}x that in wall time, {mean['compute'] * share / floor_one:.1f}x in its "
          f"share of the cores")
    peaks = list(sampler.learner_peak.values()) or [0]
    print(f"{label}, memory: learner peak RSS {max(peaks) / 1024:.0f} MiB (mean {sum(peaks) / len(peaks) / 1024:.0f}), "
          f"the learners together grew {growth(sampler.learner_series) / 1024:+.1f} MiB over the second half of their life, "
          f"whole run {sampler.total_peak / 1024 ** 2:.2f} GiB peak (PSS)")
    print(f"run directory: {run_dir}")


if __name__ == "__main__":
    main()
