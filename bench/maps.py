"""Mean/std map throughput against the matrix-multiply peak measured in the same process.

    python bench/maps.py [--passes 50] [--grid 271x201] [--threads N] [--reference-passes 10]

For each device here (the CPU, and CUDA when there is a GPU) it measures the fp32 peak
(the best of square matrix products, 1024 to 4096) and then times one map of DiNNO's
271 x 201 grid for:
- the paper's BNN (SIREN 256 -> 4 x Bayesian 256 -> 1), ``--passes`` Monte-Carlo passes, by
  :func:`predict_mean_std` (weights drawn once, passes batched);
- the same map one ordinary forward pass per draw (what the observer did before), timed on
  ``--reference-passes`` passes and scaled to ``--passes``;
- DiNNO's FourierNet [2, 256, 64, 64, 64, 1], one deterministic pass;
- bf16 where the device multiplies bf16 in hardware (AMX, AVX512-BF16 or a GPU).

Each headline is one line: case, seconds and maps per second, achieved GFLOPS (multiply-adds of
the matrix products counted twice) and the share of the measured fp32 peak.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from swarmmap.shared.learning.bnn import BayesLinear, BayesNet, fast_bf16, predict_mean_std
from swarmmap.shared.learning.networks import build_model

PAPER_BNN = [2, 256, 256, 256, 256, 256, 1]
DINNO_NET = [2, 256, 64, 64, 64, 1]


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def fp32_peak(device: torch.device) -> float:
    """Best FLOP/s of square fp32 products on ``device`` (TF32 off)."""
    torch.backends.cuda.matmul.allow_tf32 = False
    best = 0.0
    for n in (1024, 2048, 4096):
        a = torch.randn(n, n, device=device)
        b = torch.randn(n, n, device=device)
        a @ b
        sync(device)
        reps = max(3, int(2e11 / (2 * n**3)) if device.type == "cpu" else 50)
        t = time.perf_counter()
        for _ in range(reps):
            a @ b
        sync(device)
        best = max(best, 2 * n**3 * reps / (time.perf_counter() - t))
    return best


def map_flops(shape: list[int], points: int, passes: int, bayes: bool) -> float:
    """Matrix-product FLOPs of a map: the first (SIREN) layer once per point, the rest per pass."""
    first = 2 * shape[0] * shape[1]
    rest = sum(2 * a * b for a, b in zip(shape[1:-1], shape[2:]))
    return points * (first + (passes if bayes else 1) * rest)


def per_pass_reference(model: BayesNet, points: np.ndarray, passes: int, device: torch.device) -> float:
    """Seconds for ``passes`` ordinary forward passes over the grid, weights re-drawn each pass."""
    xy = torch.as_tensor(points, dtype=torch.float32, device=device)
    with torch.no_grad(), model.noise(0):
        sync(device)
        t = time.perf_counter()
        for s in range(0, len(xy), 8192):
            torch.stack([model(xy[s : s + 8192]) for _ in range(passes)]).std(0)
        sync(device)
    return time.perf_counter() - t


def timed(fn, device: torch.device, repeats: int) -> float:
    fn()  # warm-up: allocator, kernels
    best = float("inf")
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        fn()
        sync(device)
        best = min(best, time.perf_counter() - t)
    return best


def report(case: str, seconds: float, flops: float, peak: float, extra: str = "") -> None:
    rate = flops / seconds
    print(f"{case}: {seconds:.2f} s a map ({1 / seconds:.2f} maps/s), {rate / 1e9:.0f} GFLOPS, "
          f"{100 * rate / peak:.0f}% of the fp32 peak{extra}", flush=True)


def bench_device(device: torch.device, points: np.ndarray, args: argparse.Namespace) -> None:
    name = "CPU" if device.type == "cpu" else torch.cuda.get_device_name(device)
    peak = fp32_peak(device)
    print(f"{name}: fp32 peak {peak / 1e9:.0f} GFLOPS (best square product, this run, "
          f"{torch.get_num_threads() if device.type == 'cpu' else 'all'} threads)", flush=True)
    n = len(points)
    bnn = build_model(PAPER_BNN, 5.0, (0.0, 0.0, 27.1, 20.1), seed=0, kind="bnn").to(device)
    assert isinstance(bnn.seq[1], BayesLinear)
    flops = map_flops(PAPER_BNN, n, args.passes, bayes=True)
    repeats = 3 if device.type == "cpu" else 10
    fast = timed(lambda: predict_mean_std(bnn, points, samples=args.passes), device, repeats)
    report(f"paper BNN map, {args.passes} passes, {n} cells, fp32 {name}", fast, flops, peak)
    if args.reference_passes:
        ref = per_pass_reference(bnn, points, args.reference_passes, device) * args.passes / args.reference_passes
        report(f"paper BNN map, one forward pass per draw (before), fp32 {name}", ref, flops, peak,
               f"; batched is {ref / fast:.1f}x faster")
    if fast_bf16(device):
        half = timed(lambda: predict_mean_std(bnn, points, samples=args.passes, dtype=torch.bfloat16), device, repeats)
        report(f"paper BNN map, {args.passes} passes, bf16 {name}", half, flops, peak, f"; {fast / half:.2f}x fp32")
    else:
        print(f"paper BNN map, bf16 {name}: skipped, no hardware bf16 here (emulated bf16 is slower than fp32)")
    det = build_model(DINNO_NET, 5.0, (0.0, 0.0, 27.1, 20.1), seed=0).to(device)
    t = timed(lambda: predict_mean_std(det, points), device, repeats * 3)
    report(f"DiNNO FourierNet map, {n} cells, fp32 {name}", t, map_flops(DINNO_NET, n, 1, bayes=False), peak)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--passes", type=int, default=50)
    ap.add_argument("--grid", default="271x201", help="cells across x down (DiNNO's map grid by default)")
    ap.add_argument("--threads", type=int, default=0, help="CPU threads (0: torch's default, every core)")
    ap.add_argument("--reference-passes", type=int, default=10,
                    help="passes the per-pass reference is timed on (0: skip it)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    w, h = (int(v) for v in args.grid.lower().split("x"))
    xs, ys = np.meshgrid(np.linspace(0.0, 27.1, w), np.linspace(0.0, 20.1, h))
    points = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float32)
    torch.manual_seed(0)
    bench_device(torch.device("cpu"), points, args)
    if torch.cuda.is_available():
        bench_device(torch.device("cuda"), points, args)


if __name__ == "__main__":
    main()
