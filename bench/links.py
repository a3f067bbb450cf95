"""Links that decide: the team across hosts (``up --netns``) at a link rate per robot host, with
and without compression.

    sudo python bench/links.py [--preset demo] [--rounds 200] [--rates 100mbit 10mbit 1mbit]
                               [--compression none quant] [--out /tmp/links]

One ``swarmmap up --netns --link-rate RATE`` run per rate and State encoding: every robot's
services in a network namespace of its own, each robot host's link to the bridge limited to RATE
each way (tc tbf), a router per host linked in a ring over mutual TLS. Prints, per case, the
learners' median time per round (training wall time / rounds), the team's final mean val_bce,
the MB each learner sent and the run's wall time, against the fastest rate without compression.
Needs root (namespaces, tc). Runs are kept in ``--out`` and reused when their summary is there.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import up_run  # noqa: E402


def figures(summary: dict) -> tuple[float, float, float]:
    """Median seconds per round over the learners, the team's mean final val_bce, MB sent per learner."""
    rows = list(summary["learners"].values())
    per_round = statistics.median(v["wall_time_s"] / max(1, v["rounds"]) for v in rows if v["wall_time_s"])
    finals = [v["final_val_bce"] for v in rows if v["final_val_bce"] is not None]
    sent = statistics.mean(v["bytes_sent"] or 0 for v in rows) / 1e6
    return per_round, (sum(finals) / len(finals) if finals else float("nan")), sent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--robots", type=int, default=None)
    ap.add_argument("--rounds", type=int, default=200)
    ap.add_argument("--rates", nargs="+", default=["100mbit", "10mbit", "1mbit"])
    ap.add_argument("--compression", nargs="+", default=["none", "quant"])
    ap.add_argument("--out", type=Path, default=Path("/tmp/links"))
    a = ap.parse_args()
    base = ["--preset", a.preset, "--no-observer", "--netns", "--rounds", str(a.rounds)]
    base += ["--robots", str(a.robots)] if a.robots else []
    a.out.mkdir(parents=True, exist_ok=True)
    reference = None
    for compression in a.compression:
        for rate in a.rates:
            run_dir = a.out / f"{rate}-{compression}"
            summary = up_run(run_dir, base + ["--link-rate", rate, "--set", f"learner.compression={compression}"])
            per_round, mean, sent = figures(summary)
            reference = reference or (per_round, mean)
            case = f"{a.preset} team ({summary['robots']} robots, {a.rounds} rounds), {rate} per robot link, compression {compression}"
            print(f"{case}: {per_round:.3f} s a round ({per_round / reference[0]:.2f}x the first case), final mean val_bce "
                  f"{mean:.4f} ({100 * (mean / reference[1] - 1):+.1f}%), {sent:.1f} MB sent a learner; ended by itself: "
                  f"{summary['ok'] or summary['reason']}; {summary['wall_time_s']:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
