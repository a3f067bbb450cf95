"""How round time and memory grow with the team: 2 to 32 learner processes, work per learner held.

    python bench/scale.py [--teams 2,4,8,16,32] [--rounds 60] [--graph ring] [--repeat 3]

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

The machine's speed drifts from minute to minute on a shared host (the same 2-learner run
took 11.7 to 19.0 ms a round per learner here), so every team size runs ``--repeat`` times,
interleaved (2, 4, .., 32, then again), and the headline compares medians.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path
from statistics import median

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
    ap.add_argument("--repeat", type=int, default=3, help="runs of every team size, interleaved (2, 4, .., 32, 2, 4, ..)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a further setting for every run, as swarmmap up --set")
    ap.add_argument("--keep", type=Path, default=None, help="keep the run directories here")
    args = ap.parse_args()
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench-scale-"))
    teams = [int(v) for v in args.teams.split(",")]
    per_learner: dict[int, list[float]] = {n: [] for n in teams}
    for rep in range(args.repeat):
        for n in teams:
            value = run_team(args, n, base / f"team-{n}" if args.repeat == 1 else base / f"team-{n}-{rep + 1}")
            if value is not None:
                per_learner[n].append(value)
    done = [n for n in teams if per_learner[n]]
    if len(done) < 2:
        return
    first = median(per_learner[done[0]])
    for n in done:
        v = per_learner[n]
        print(f"team of {n}: {median(v) * 1e3:.1f} ms a round per learner, median of {len(v)} "
              f"({min(v) * 1e3:.1f}-{max(v) * 1e3:.1f}), {median(v) / first:.2f}x linear from the team of {done[0]}", flush=True)
    last = median(per_learner[done[-1]])
    print(f"scale, {done[0]} -> {done[-1]} learners, tiny model {args.shape}, {args.graph} graph: {last / first:.2f}x linear "
          f"({first * 1e3:.1f} -> {last * 1e3:.1f} ms a round per learner, medians of {args.repeat} interleaved runs; "
          f"1.00x is a team round growing linearly with the team)", flush=True)


def run_team(args: argparse.Namespace, n: int, run_dir: Path) -> float | None:
    """One ``swarmmap up`` of ``n`` learners: prints its line and returns seconds a round per learner."""
    cmd = [sys.executable, "-m", "swarmmap.services.cli", "up", "--preset", "smoke", "--robots", str(n),
           "--rounds", str(args.rounds), "--no-observer", "--run-dir", str(run_dir),
           "--set", f"learner.graph={args.graph}", "--set", f"learner.model_shape=[{args.shape}]",
           "--set", f"learner.batch_size={args.batch}", "--set", f"learner.eval_every={args.rounds // 3}",
           "--set", "learner.checkpoint_every=0"] + [a for kv in args.sets for a in ("--set", kv)]
    status, err, wall, sampler = run_sampled(cmd, env=os.environ | {"OMP_NUM_THREADS": "1"})
    if status != 0:
        print(f"team of {n}: swarmmap up failed ({status}): {err[-1500:]}", flush=True)
        return None
    start = per_round(run_dir, {"round": "wall_time_s"})["round"]  # from round 0: with the learners' staggered start
    rt = per_round(run_dir, {"round": "wall_time_s"}, from_round=args.rounds // 3)["round"]
    peaks = list(sampler.learner_peak.values()) or [0]
    cpu = sampler.cpu_by_service()
    print(f"team of {n} learners, tiny model {args.shape}, {args.graph} graph: {rt:.3f} s a round, "
          f"{rt / n * 1e3:.1f} ms a round per learner, "
          f"learner peak RSS {max(peaks) / 1024:.0f} MiB (mean {sum(peaks) / len(peaks) / 1024:.0f}), "
          f"whole run {sampler.total_peak / 1024 ** 2:.2f} GiB peak (PSS), {wall:.0f} s wall; "
          f"from round 0, with the staggered start: {start:.3f} s a round; CPU seconds by service: "
          + ", ".join(f"{k} {v:.1f}" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1]))
          + f"; this bench's memory sampling {sampler.own_cpu_s:.1f}", flush=True)
    return rt / n


if __name__ == "__main__":
    main()
