"""Time-to-quality curves of finished runs: mean validation BCE over the robots against wall time.

    python bench/time_to_quality.py RUN_DIR[=label] ... [--target 0.102] [--out curves.png]

For each run directory (``swarmmap up``'s) it reads ``metrics.csv`` and ``summary.json``,
averages ``val_bce`` over the robots at every evaluated round (a round counts once every
robot has reported it) and places it at the latest robot's ``wall_time_s`` (seconds since the
learners started training) plus the run's start-up and traversal (``summary.json``'s wall time
less the learners' last: an upper bound, as it also holds the shut-down). It prints, per run, when the mean first
reached ``--target`` and the final mean, and draws the curves.
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def curve(run_dir: Path) -> tuple[list[int], list[float], list[float], float]:
    """Rounds, seconds since the run started, mean val_bce; and the run's start-up before training."""
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))
    by_round: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_round[int(r["round"])].append(r)
    # The learners that report from round 0 (a centralized run has one, its copies report only at the end).
    learners = {r["robot"] for r in by_round[min(by_round)]}
    robots = len(learners)
    summary = json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").exists() else {}
    last = max(float(r["wall_time_s"]) for r in rows)
    # Start-up and traversal: the run's whole wall time less the learners' (their clock starts with
    # training); this also counts the shut-down, so the times are upper bounds.
    startup = max(0.0, float(summary.get("wall_time_s", last)) - last)
    rounds, times, means = [], [], []
    for k in sorted(by_round):
        mine = {r["robot"]: r for r in by_round[k] if r["robot"] in learners}
        if len(mine) != robots:
            continue
        rounds.append(k)
        times.append(startup + max(float(r["wall_time_s"]) for r in mine.values()))
        means.append(sum(float(r["val_bce"]) for r in mine.values()) / robots)
    return rounds, times, means, startup


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="RUN_DIR or RUN_DIR=label")
    ap.add_argument("--target", type=float, default=0.102)
    ap.add_argument("--out", type=Path, default=Path("time_to_quality.png"))
    args = ap.parse_args()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for spec in args.runs:
        path, _, label = spec.partition("=")
        run_dir = Path(path)
        label = label or run_dir.name
        rounds, times, means, startup = curve(run_dir)
        hit = next(((k, t) for k, t, m in zip(rounds, times, means) if m <= args.target), None)
        when = f"reached {args.target} at round {hit[0]}, {hit[1]:.0f} s" if hit else f"never reached {args.target}"
        print(f"{label}: {when}; final mean val_bce {means[-1]:.4f} at round {rounds[-1]}, {times[-1]:.0f} s "
              f"(start-up and traversal {startup:.0f} s)", flush=True)
        ax.plot(times, means, marker=".", label=label)
    ax.axhline(args.target, color="grey", linestyle="--", linewidth=1)
    ax.set_xlabel("wall time since the run started (s)")
    ax.set_ylabel("mean validation BCE over robots")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"curves: {args.out}")


if __name__ == "__main__":
    main()
