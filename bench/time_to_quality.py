"""Time-to-quality curves of finished runs: mean validation BCE over the robots against wall time.

    python bench/time_to_quality.py RUN_DIR[=label] ... [--target 0.102] [--out curves.png]

For each run directory (``swarmmap up``'s) it reads ``metrics.csv`` and ``summary.json``,
averages ``val_bce`` over the robots at every evaluated round (a round counts once every
robot has reported it) and places it at the latest robot's ``wall_time_s`` (seconds since the
learners started training) plus the run's start-up and traversal (``summary.json``'s wall time
less the learners' last: an upper bound, as it also holds the shut-down). It prints, per run, when the mean first
reached ``--target`` and the final mean, and draws the curves against round and wall time.
It is ``swarmmap compare`` with DiNNO's published quality (0.102) as the default target.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from swarmmap.services.runs import ToolError, compare


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="RUN_DIR or RUN_DIR=label")
    ap.add_argument("--target", type=float, default=0.102)
    ap.add_argument("--out", type=Path, default=Path("time_to_quality.png"))
    try:
        return compare(ap.parse_args())
    except ToolError as exc:
        print(exc, file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
