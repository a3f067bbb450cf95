"""The team on a real log beside its peers: swarmmap's BNN with sigma, dinno and DGVI's consensus, one
robot with all the data, and the classic log-odds grid, all scored on the same held-out scans.

    python bench/datasets.py [--log ../shared/data/carmen/intel-corrected.log.gz] [--robots 4]
                             [--preset demo] [--rounds N] [--out /tmp/datasets]

One ``swarmmap up --dataset LOG --model bnn`` run per case (kept in ``--out`` and reused when its
summary is there). Prints, per case, the robots' mean held-out val_bce, their maps' NLL and
calibration error (ECE) at the held-out points (``swarmmap experiment score``), and the bytes each
robot sent; then the log-odds grid's on the same points, and a Markdown table of it all.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import Runs, up_run  # noqa: E402

from swarmmap.services.experiments.score import reference_row, score_run  # noqa: E402
from tests.conftest import KIT_DATA  # noqa: E402

CASES = {  # run folder: (case, options)
    "sigma": ("BNN, sigma consensus", ["--set", "learner.consensus=sigma"]),
    "dinno": ("BNN, DiNNO's consensus", ["--set", "learner.consensus=dinno"]),
    "dgvi": ("BNN, DGVI's consensus", ["--set", "learner.consensus=dgvi"]),
    "centralized": ("BNN, one robot with all the data", ["--algorithm", "centralized", "--transport", "inproc"]),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", type=Path, default=KIT_DATA / "carmen" / "intel-corrected.log.gz")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--out", type=Path, default=Path("/tmp/datasets"))
    a = ap.parse_args()
    base = ["--dataset", str(a.log), "--robots", str(a.robots), "--preset", a.preset, "--model", "bnn", "--no-observer"]
    base += ["--rounds", str(a.rounds)] if a.rounds else []
    a.out.mkdir(parents=True, exist_ok=True)
    rows, name = [], a.log.name.split(".")[0]
    runs = Runs(len(CASES))
    for folder, (case, extra) in CASES.items():
        run_dir = a.out / folder
        summary = up_run(run_dir, base + extra)
        runs.ended(folder)
        if not summary["ok"]:
            print(f"{case}: the run failed: {summary['reason']}", flush=True)
            continue
        learners = summary["learners"].values()
        val = sum(v["final_val_bce"] for v in learners) / len(learners)
        scores = score_run(run_dir)
        nll = sum(s["nll"] for s in scores.values()) / len(scores)
        ece = sum(s["ece"] for s in scores.values()) / len(scores)
        sent = sum(v["bytes_sent"] or 0 for v in learners) / len(learners)
        rows.append((case, val, nll, ece, sent, summary["wall_time_s"]))
        print(f"{name}, {a.robots} robots, {case}: held-out val_bce {val:.4f} against the log-odds grid's "
              f"{summary['reference']['val_bce']:.4f}; NLL {nll:.4f}, ECE {ece:.4f} at the held-out points; "
              f"{sent / 1e6:.1f} MB sent per robot; {summary['wall_time_s']:.0f} s", flush=True)
    ref = reference_row(run_dir)
    print(f"{name}, log-odds grid of every training scan: held-out val_bce {ref['nll']:.4f}, ECE {ref['ece']:.4f}, "
          "nothing sent", flush=True)
    print("\n| case | held-out val_bce | NLL at the held-out points | ECE | MB sent per robot | wall time |")
    print("| --- | --- | --- | --- | --- | --- |")
    for case, val, nll, ece, sent, wall in rows:
        print(f"| {case} | {val:.4f} | {nll:.4f} | {ece:.4f} | {sent / 1e6:.1f} | {wall / 60:.0f} min |")
    print(f"| log-odds grid of every training scan | {ref['nll']:.4f} | {ref['nll']:.4f} | {ref['ece']:.4f} | 0 | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
