"""Links that decide: the team across hosts (``up --netns``) at a link rate per robot host, with
and without compression.

    sudo python bench/links.py [--preset demo] [--model bnn] [--rounds 200] [--rates 100mbit 10mbit 1mbit]
                               [--compression none quant adaptive] [--out /tmp/links]

One ``swarmmap up --netns --link-rate RATE`` run per rate and State encoding: every robot's
services in a network namespace of its own, each robot host's link to the bridge limited to RATE
each way (tc tbf), a router per host linked in a ring over mutual TLS. ``adaptive`` is
compression none with ``learner.slow_link_compression=quant``: each learner switches to quant
on its own when its links, not its training, set the pace. Prints, per case, the
learners' median time per round (training wall time / rounds), the team's final mean val_bce,
the MB each learner sent and the run's wall time, against the fastest rate without compression.
Needs root (namespaces, tc). Runs are kept in ``--out`` and reused when their summary is there.
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import Runs, up_run  # noqa: E402

# What each --compression case sets.
ENCODINGS = {name: ["--set", f"learner.compression={name}"] for name in ("none", "f16", "bf16", "quant")}
ENCODINGS["adaptive"] = ["--set", "learner.compression=none", "--set", "learner.slow_link_compression=quant"]


def figures(summary: dict) -> tuple[float, float, float]:
    """Median seconds per round over the learners, the team's mean final val_bce, MB sent per learner."""
    rows = list(summary["learners"].values())
    times = [v["wall_time_s"] / max(1, v["rounds"]) for v in rows if v["wall_time_s"]]
    per_round = statistics.median(times) if times else float("nan")  # a run that failed before training
    finals = [v["final_val_bce"] for v in rows if v["final_val_bce"] is not None]
    sent = statistics.mean(v["bytes_sent"] or 0 for v in rows) / 1e6
    return per_round, (sum(finals) / len(finals) if finals else float("nan")), sent


def switched(run_dir: Path) -> str:
    """How many learners switched their States' encoding on their own (learner.slow_link_compression), and when."""
    rounds = sorted(int(m[1]) for log in (run_dir / "logs").glob("learner-*.log")
                    if (m := re.search(r"set the pace; its States go out as .* from round (\d+)", log.read_text())))
    return f"; {len(rounds)} learners switched their encoding, at rounds {rounds}" if rounds else ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--robots", type=int, default=None)
    ap.add_argument("--rounds", type=int, default=200)
    ap.add_argument("--rates", nargs="+", default=["100mbit", "10mbit", "1mbit"])
    ap.add_argument("--compression", nargs="+", default=["none", "quant", "adaptive"], choices=list(ENCODINGS))
    ap.add_argument("--model", default=None, help="the learners' model (default the preset's), e.g. bnn")
    ap.add_argument("--out", type=Path, default=Path("/tmp/links"))
    a = ap.parse_args()
    # Namespaces share /dev/shm: without Zenoh's shared memory the links carry every byte of the States.
    base = ["--preset", a.preset, "--no-observer", "--netns", "--rounds", str(a.rounds), "--set", "zenoh.shared_memory=false"]
    base += ["--model", a.model] if a.model else []
    base += ["--robots", str(a.robots)] if a.robots else []
    a.out.mkdir(parents=True, exist_ok=True)
    reference, model = None, a.model or "the preset's model"
    runs = Runs(len(a.compression) * len(a.rates))
    for compression in a.compression:
        for rate in a.rates:
            run_dir = a.out / f"{rate}-{compression}"
            summary = up_run(run_dir, base + ["--link-rate", rate, *ENCODINGS[compression]])
            runs.ended(run_dir.name)
            per_round, mean, sent = figures(summary)
            reference = reference or (per_round, mean)
            case = (f"{a.preset} team ({summary['robots']} robots, {model}, {a.rounds} rounds), {rate} per robot link, "
                    f"compression {compression}")
            print(f"{case}: {per_round:.3f} s a round ({per_round / reference[0]:.2f}x the first case), final mean val_bce "
                  f"{mean:.4f} ({100 * (mean / reference[1] - 1):+.1f}%), {sent:.1f} MB sent a learner; ended by itself: "
                  f"{summary['ok'] or summary['reason']}; {summary['wall_time_s']:.0f} s{switched(run_dir)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
