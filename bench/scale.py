"""How round time and memory grow with the team: 2 to 32 learner processes, work per learner held.

    python bench/scale.py [--teams 2,4,8,16,32] [--rounds 60] [--graph ring]

For each team size N it runs ``swarmmap up`` (smoke plan, every learner its own process over
Zenoh, no observer) with a tiny model and the same work per learner: batch, primal
iterations and a fixed-degree graph (``ring``: two neighbours each, so that a learner's
exchange does not grow with N; ``--graph complete`` shows the all-to-all cost). It samples
the resident memory of every process of the run (``/proc``, every 0.25 s) and reads the
learners' Metrics. Printed per N: seconds a round in the steady state (from the Metrics of
round rounds/3 to the last: the learners start Algorithm 1 up to seconds apart as their
processes come up, and the first rounds wait for the last to start; the figure from round 0 is
printed too), seconds a round per learner (on a fixed number of cores the team's round
time should grow linearly with N: this is its ratio to the 2-learner team's), peak resident
memory of a learner, and of the whole run (every service). ``--robots-per-room`` is not
needed: the smoke plan's paths are shared out however many robots there are.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from procmem import run_sampled  # noqa: E402
from rounds import per_round  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--teams", default="2,4,8,16,32")
    ap.add_argument("--rounds", type=int, default=60)
    ap.add_argument("--graph", default="ring", choices=["ring", "complete"])
    ap.add_argument("--shape", default="2,32,32,1", help="the tiny model's layer widths")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--keep", type=Path, default=None, help="keep the run directories here")
    args = ap.parse_args()
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench-scale-"))
    first = None
    for n in [int(v) for v in args.teams.split(",")]:
        run_dir = base / f"team-{n}"
        cmd = [sys.executable, "-m", "swarmmap.services.cli", "up", "--preset", "smoke", "--robots", str(n),
               "--rounds", str(args.rounds), "--no-observer", "--run-dir", str(run_dir),
               "--set", f"learner.graph={args.graph}", "--set", f"learner.model_shape=[{args.shape}]",
               "--set", f"learner.batch_size={args.batch}", "--set", f"learner.eval_every={args.rounds // 3}",
               "--set", "learner.checkpoint_every=0"]
        status, err, wall, sampler = run_sampled(cmd, env=os.environ | {"OMP_NUM_THREADS": "1"})
        if status != 0:
            print(f"team of {n}: swarmmap up failed ({status}): {err[-1500:]}", flush=True)
            continue
        start = per_round(run_dir, {"round": "wall_time_s"})["round"]  # from round 0: with the learners' staggered start
        rt = per_round(run_dir, {"round": "wall_time_s"}, from_round=args.rounds // 3)["round"]
        per_learner = rt / n
        first = first or per_learner
        peaks = list(sampler.learner_peak.values()) or [0]
        print(f"team of {n} learners, tiny model {args.shape}, {args.graph} graph: {rt:.3f} s a round, "
              f"{per_learner * 1e3:.1f} ms a round per learner ({per_learner / first:.2f}x linear from the first team), "
              f"learner peak RSS {max(peaks) / 1024:.0f} MiB (mean {sum(peaks) / len(peaks) / 1024:.0f}), "
              f"whole run {sampler.total_peak / 1024 ** 2:.2f} GiB peak (PSS), {wall:.0f} s wall; "
              f"from round 0, with the staggered start: {start:.3f} s a round", flush=True)
        cpu = sampler.cpu_by_service()
        print(f"team of {n}: CPU seconds by service: " + ", ".join(f"{k} {v:.1f}" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1])),
              flush=True)


if __name__ == "__main__":
    main()
