"""Render a run's Rerun recording in a headless viewer and save a screenshot (the README's).

    python bench/viewer_screenshot.py RUN_DIR/recording.rrd viewer.png [--round N] [--size 1600x900]

Spawns ``rerun --headless`` (needs a Vulkan adapter: a GPU, or Mesa's lavapipe from Debian's
``mesa-vulkan-drivers`` package), opens the recording with its blueprint, puts the time cursor
on the ``round`` timeline's last round (or ``--round``) and saves the whole viewer as PNG.
"""

from __future__ import annotations

import argparse
import socket
import time
from pathlib import Path

from rerun.chunk import RrdReader
from rerun.experimental import ViewerClient


def last_round(path: Path) -> int:
    """The largest ``round`` any chunk of the recording holds."""
    best = 0
    for chunk in RrdReader(path).stream():
        if "round" in chunk.timeline_names:
            col = chunk.to_record_batch().column("round")
            best = max(best, max(int(v) for v in col.to_pylist() if v is not None))
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--round", type=int, default=None, help="round to show (default: the last)")
    ap.add_argument("--settle-s", type=float, default=5.0, help="seconds to let the viewer load and lay out")
    args = ap.parse_args()
    rnd = last_round(args.recording) if args.round is None else args.round
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = ViewerClient.spawn(headless=True, port=port, hide_welcome_screen=True)
    try:
        viewer.open(str(args.recording.resolve()))
        time.sleep(args.settle_s)
        viewer.set_time("round", sequence=rnd, play_state="paused")
        time.sleep(1.0)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        viewer.save_screenshot(str(args.out.resolve()))
    finally:
        viewer.quit()
    print(f"{args.out}: round {rnd} of {args.recording}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
