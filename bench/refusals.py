"""How fast the command line answers a mistake or a question: wall time of each command below,
run in an empty folder (the goal: a refusal or a finished run's status within 10 s).

    python bench/refusals.py [--finished RUN_DIR] [--repeat 3]

Commands: ``up --floorplan missing.svg``, ``prepare --floorplan missing.svg``, ``up --preset
smoke`` with a misspelt ``SWARMMAP_LERNER__ROUNDS``, ``up --device cuda`` (refused where there
is no CUDA device), ``--version``, and with ``--finished`` ``status RUN_DIR`` of a finished run.
Prints each command's exit status and its median, min and max seconds.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SWARMMAP = [sys.executable, "-m", "swarmmap.services.cli"]


def timed(args: list[str], env: dict[str, str], cwd: str) -> tuple[int, float]:
    start = time.monotonic()
    proc = subprocess.run([*SWARMMAP, *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)
    return proc.returncode, time.monotonic() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--finished", type=Path, default=None, help="a finished run directory, for status")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    base = {k: v for k, v in os.environ.items() if not k.startswith("SWARMMAP_")}
    cases = [("up --floorplan missing.svg", ["up", "--floorplan", "missing.svg"], {}),
             ("prepare --floorplan missing.svg", ["prepare", "--floorplan", "missing.svg"], {}),
             ("SWARMMAP_LERNER__ROUNDS=3 up --preset smoke", ["up", "--preset", "smoke"], {"SWARMMAP_LERNER__ROUNDS": "3"}),
             ("up --preset smoke --device cuda", ["up", "--preset", "smoke", "--device", "cuda"], {}),
             ("--version", ["--version"], {})]
    if args.finished is not None:
        cases.append((f"status {args.finished}", ["status", str(args.finished.resolve())], {}))
    print(f"{'command':<48} {'status':>6} {'median s':>9} {'min s':>7} {'max s':>7}")
    for label, argv, extra in cases:
        with tempfile.TemporaryDirectory() as cwd:
            results = [timed(argv, {**base, **extra}, cwd) for _ in range(args.repeat)]
            left = os.listdir(cwd)
        secs = [t for _, t in results]
        print(f"{label:<48} {results[0][0]:>6} {statistics.median(secs):>9.2f} {min(secs):>7.2f} {max(secs):>7.2f}"
              + (f"  (left {left} behind)" if left else ""), flush=True)


if __name__ == "__main__":
    main()
