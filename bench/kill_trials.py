"""Kill a random learner at a random round of a real ``swarmmap up`` run, many times, and tally.

    python bench/kill_trials.py [--trials 100] [--rounds 200] [--robots 3] [--out /tmp/kill-trials]

One clean run, then per trial a run (smoke preset, Zenoh, one process per learner) in which
``tests/harness.py`` sends SIGKILL to learner r at round k (r and k drawn from a seeded RNG).
Prints one line per trial and the tally: runs that finished with exit 0, restarted learners
that rejoined, runs whose every robot ended within 5% of the clean run's final val_bce, the
largest deviation, and runs that left a process behind or hung (a run gets 10 minutes).
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.harness

from tests.harness import final_losses, kill_at_round, leftovers, up  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=200)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("/tmp/kill-trials"))
    a = ap.parse_args()
    args = ["--preset", "smoke", "--robots", str(a.robots), "--rounds", str(a.rounds), "--no-observer"]
    clean_dir = a.out / "clean"
    if not (clean_dir / "summary.json").exists():
        assert up(clean_dir, *args).wait(600) == 0, f"the clean run failed; see {clean_dir}"
    clean = final_losses(clean_dir)
    tally = {"finished": 0, "rejoined": 0, "within_5pct": 0, "leftovers": 0, "hung": 0}
    worst = 0.0
    for trial in range(a.trials):
        rng = random.Random(trial)
        robot, at, after = rng.randrange(a.robots), rng.randrange(10, a.rounds - 40), rng.uniform(0, 1.5)
        run_dir = a.out / f"trial-{trial}"
        shutil.rmtree(run_dir, ignore_errors=True)  # the bench's own trial of an earlier call: up refuses a finished run
        t0 = time.monotonic()
        proc = up(run_dir, *args)
        try:
            kill_at_round(run_dir, "learner", robot, at, after_s=after)
            code = proc.wait(600)
        except Exception as exc:  # a hang or a kill that never came: counted, and the next trial goes on
            proc.kill()
            code = None
            print(f"trial {trial}: {exc}")
        if code is None:
            tally["hung"] += 1
            continue
        summary = json.loads((run_dir / "summary.json").read_text())
        deviation = max(abs(v - clean[r]) / clean[r] for r, v in final_losses(run_dir).items())
        rejoined = summary["services"][f"learner-{robot}"]["restarts"] == 1 and summary["learners"][str(robot)]["finished"]
        left = leftovers(run_dir)
        tally["finished"] += code == 0
        tally["rejoined"] += rejoined
        tally["within_5pct"] += deviation <= 0.05
        tally["leftovers"] += bool(left)
        worst = max(worst, deviation)
        print(f"trial {trial}: learner {robot} killed {after:.1f} s after round {at}: exit {code}, rejoined {rejoined}, "
              f"largest deviation {100 * deviation:.1f}%, {time.monotonic() - t0:.0f} s", flush=True)
    n = a.trials
    print(f"learner killed at a random round, {a.robots} robots x {a.rounds} rounds (smoke): {tally['finished']}/{n} runs "
          f"exit 0, {tally['rejoined']}/{n} learners restarted and rejoined, {tally['within_5pct']}/{n} runs with every "
          f"robot within 5% of the clean run's val_bce (largest deviation {100 * worst:.1f}%), "
          f"{tally['leftovers']} with a process left behind, {tally['hung']} hung")
    return 0 if tally["finished"] == n else 1


if __name__ == "__main__":
    sys.exit(main())
