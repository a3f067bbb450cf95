"""Ctrl-C at any moment: how long ``swarmmap up`` takes to return, with what status, and what it leaves.

    python bench/interrupts.py [--at 1 3 5 10 20 40] [--trials 5] [--load] [--out /tmp/interrupts]

Each trial starts ``swarmmap up --preset smoke --no-observer`` in a process group of its own (as a
terminal's foreground job) and, ``--at`` seconds later, sends SIGINT to the whole group, as
Ctrl-C does. It records the seconds until ``up`` returned, its exit status, the run's processes
still alive a second after it returned, and whether its closing block names ``--resume``.
``--load`` runs a second smoke run beside each trial (a loaded machine). Prints one line per
moment and a headline: the slowest return against ``up.stop_grace_s`` + 5 s.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import SWARMMAP, clean_env  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.harness import leftovers  # noqa: E402

GRACE_S = 10.0  # up.stop_grace_s's default


def trial(run_dir: Path, at: float) -> tuple[float, int, list[int], bool]:
    """(seconds to return, exit status, processes left, --resume named) of one Ctrl-C ``at`` s in."""
    log = open(f"{run_dir}.log", "w")
    proc = subprocess.Popen([*SWARMMAP, "up", "--run-dir", str(run_dir), "--preset", "smoke", "--no-observer", "--rounds", "400"],
                            stdout=log, stderr=subprocess.STDOUT, env=clean_env(), start_new_session=True)
    time.sleep(at)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    try:
        code = proc.wait(timeout=300)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        code = proc.wait()
    took = time.monotonic() - t0
    time.sleep(1.0)
    left = leftovers(run_dir)
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    return took, code, left, "--resume" in Path(f"{run_dir}.log").read_text(errors="replace")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--at", nargs="+", type=float, default=[1, 3, 5, 10, 20, 40])
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--load", action="store_true", help="a second smoke run beside each trial")
    ap.add_argument("--out", type=Path, default=Path("/tmp/interrupts"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    worst, bad = 0.0, 0
    for at in a.at:
        rows = []
        for k in range(a.trials):
            load = None
            if a.load:
                load = subprocess.Popen([*SWARMMAP, "up", "--run-dir", str(a.out / f"load-{at:g}-{k}"), "--preset", "smoke",
                                         "--no-observer", "--rounds", "400"], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                                        env=clean_env(), start_new_session=True)
            rows.append(trial(a.out / f"at-{at:g}-{k}", at))
            if load is not None:
                os.killpg(load.pid, signal.SIGINT)
                load.wait(300)
        took = [r[0] for r in rows]
        worst = max(worst, *took)
        wrong = [r for r in rows if r[1] != 130 or r[2]]
        bad += len(wrong)
        print(f"Ctrl-C {at:g} s into a smoke run{' (a second run beside it)' if a.load else ''}: returned in "
              f"{min(took):.1f}-{max(took):.1f} s over {len(rows)} trials; exit {sorted({r[1] for r in rows})}; processes left "
              f"{sum(len(r[2]) for r in rows)}; --resume named {sum(r[3] for r in rows)} of {len(rows)}", flush=True)
    print(f"Ctrl-C, smoke runs: slowest return {worst:.1f} s against up.stop_grace_s + 5 = {GRACE_S + 5:.0f} s; "
          f"{bad} trial(s) without exit 130 or with a process left", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
