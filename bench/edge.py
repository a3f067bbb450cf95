"""Robots on an edge device's budget: each model at each budget against the same run with none.

    sudo python bench/edge.py [--cases demo quickstart paper] [--budgets 1G,1 512M,0.5 384M,0.25]
                              [--robots N] [--rounds N] [--out /tmp/bench/edge]

For each case (``demo``: the demo's FourierNet; ``quickstart``: its BNN; ``paper``: the paper's
BNN) one ``swarmmap up`` with no budget, then one per budget (``up --budget``, a Linux control
group per robot: root). A budget the run's robots cannot fit in is refused at start, naming the
smallest that fits; the bench prints that. Per run: each robot's peak memory (its control group's;
the unbudgeted run's from a budget of 64 GiB, which holds nothing back), the times its memory
reached the limit, seconds a round (the learners' wall time over their rounds, the mean), the final
mean val_bce and its ratio to the unbudgeted run's. Runs are kept in ``--out`` and reused."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import SWARMMAP, Runs, clean_env  # noqa: E402

CASES = {"demo": ["--preset", "demo"], "quickstart": ["--preset", "quickstart"], "paper": ["--preset", "paper"]}
UNLIMITED = "64G,64"  # the unbudgeted run, measured the same way (a group that holds nothing back)


def run(run_dir: Path, args: list[str], budget: str) -> dict:
    """The run's summary, or ``{"refused": why}`` where ``up`` refused its budget at start."""
    refused = run_dir.with_suffix(".refused")
    if refused.exists():
        return {"refused": refused.read_text()}
    if not (run_dir / "summary.json").exists():
        t0 = time.monotonic()
        with open(f"{run_dir}.log", "a") as out:
            done = subprocess.run([*SWARMMAP, "up", "--run-dir", str(run_dir), "--no-observer", "--budget", budget, *args],
                                  stdout=out, stderr=subprocess.PIPE, text=True, env=clean_env(), timeout=6 * 3600)
            out.write(done.stderr)
        print(f"  ({run_dir.name}: {time.monotonic() - t0:.0f} s)", flush=True)
        if done.returncode == 2 and "The smallest budget that fits" in done.stderr:
            why = done.stderr.split("up.budget: ")[1].strip()
            refused.write_text(why)
            return {"refused": why}
    return json.loads((run_dir / "summary.json").read_text())


def figures(summary: dict) -> dict:
    learners = summary["learners"].values()
    robots = summary["budget"]["robots"].values()
    return {"peak_mib": max(r["peak_memory_bytes"] for r in robots) / 1024**2,
            "limit_hits": sum(r.get("limit_hits", 0) for r in robots),
            "s_round": sum(v["wall_time_s"] / max(v["rounds"], 1) for v in learners) / len(learners),
            "val_bce": sum(v["final_val_bce"] for v in learners) / len(learners),
            "ok": summary["ok"], "reason": summary.get("reason", "")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    ap.add_argument("--budgets", nargs="+", default=["1G,1", "512M,0.5", "384M,0.25"])
    ap.add_argument("--robots", type=int, default=None)
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench/edge"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    extra = (["--robots", str(a.robots)] if a.robots else []) + (["--rounds", str(a.rounds)] if a.rounds else [])
    runs = Runs(len(a.cases) * (1 + len(a.budgets)))
    for case in a.cases:
        args = CASES[case] + extra
        free = run(a.out / f"{case}-none", args, UNLIMITED)
        runs.ended(f"{case}, no budget")
        if "refused" in free or not free["ok"]:
            print(f"{case}, no budget: did not finish ({free.get('refused') or free.get('reason')})", flush=True)
            continue
        ref = figures(free)
        print(f"{case}, no budget: peak {ref['peak_mib']:.0f} MiB a robot, {ref['s_round']:.2f} s a round, "
              f"final val_bce {ref['val_bce']:.4f}", flush=True)
        for budget in a.budgets:
            summary = run(a.out / f"{case}-{budget.replace(',', '_')}", args, budget)
            runs.ended(f"{case}, {budget}")
            if "refused" in summary:
                print(f"{case}, budget {budget}: refused at start: {summary['refused']}", flush=True)
                continue
            f = figures(summary)
            print(f"{case}, budget {budget}: peak {f['peak_mib']:.0f} MiB a robot (limit reached {f['limit_hits']} times), "
                  f"{f['s_round']:.2f} s a round ({f['s_round'] / ref['s_round']:.2f}x no budget), final val_bce "
                  f"{f['val_bce']:.4f} ({100 * (f['val_bce'] / ref['val_bce'] - 1):+.1f}% against no budget)"
                  + ("" if f["ok"] else f"; did not finish: {f['reason']}"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
