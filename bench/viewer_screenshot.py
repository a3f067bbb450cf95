"""Render a run's Rerun recording in a headless viewer and save a screenshot (the README's).

    python bench/viewer_screenshot.py RUN_DIR/recording.rrd viewer.png [--round N] [--size 1600x900]

Starts ``rerun --headless`` (needs a Vulkan adapter: a GPU, or Mesa's lavapipe from Debian's
``mesa-vulkan-drivers`` package), opens the recording with its blueprint, puts the time cursor
on the ``round`` timeline's last round (or ``--round``) and saves the whole viewer as PNG
through the viewer's control API (``rerun.experimental.ViewerClient``).
"""

from __future__ import annotations

import argparse
import socket
import subprocess
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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--round", type=int, default=None, help="round to show (default: the last)")
    ap.add_argument("--size", default="1400x800", help="viewer size in logical points, WIDTHxHEIGHT")
    ap.add_argument("--settle-s", type=float, default=6.0, help="seconds to let the viewer load and lay out")
    args = ap.parse_args()
    rnd = last_round(args.recording) if args.round is None else args.round
    port = free_port()
    viewer = subprocess.Popen(["rerun", "--headless", "--port", str(port), "--hide-welcome-screen",
                               "--window-size", args.size], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        client = None
        deadline = time.monotonic() + 30
        while client is None:
            try:
                client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
                client.get_state()
            except Exception:  # not listening yet
                client = None
                if time.monotonic() > deadline or viewer.poll() is not None:
                    raise SystemExit("the headless viewer did not start (is there a Vulkan adapter, e.g. mesa-vulkan-drivers?)")
                time.sleep(0.5)
        client.open(str(args.recording.resolve()))
        time.sleep(args.settle_s)
        client.set_time("round", sequence=rnd, play_state="paused")
        time.sleep(2.0)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_bytes(client.take_screenshot(max_size=int(args.size.split("x")[0])))
    finally:
        viewer.terminate()
        viewer.wait(10)
    print(f"{args.out}: round {rnd} of {args.recording}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
