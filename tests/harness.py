"""The fault-injection harness for whole runs (tests and bench/): start ``swarmmap up``, kill a
chosen service at a chosen round, and check that no process of the run is left behind.
Message loss, duplication and delay between chosen nodes come from the run's ``faults``
settings (``--set faults.link_success=0.7``, see services/learner/faults.py)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

from tests.conftest import SWARMMAP, clean_env


def up(run_dir: Path, *args: str) -> subprocess.Popen:
    """``swarmmap up --run-dir run_dir args`` in the background, its output in run_dir.up.log."""
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    out = open(f"{run_dir}.up.log", "w")
    return subprocess.Popen([*SWARMMAP, "up", "--run-dir", str(run_dir), *args], stdout=out, stderr=subprocess.STDOUT,
                            env=clean_env())


def reported_round(run_dir: Path, robot: int) -> int:
    """The newest round ``robot`` reported metrics for (-1 before any)."""
    try:
        text = (run_dir / "logs" / "recorder-0.log").read_text()
    except OSError:
        return -1
    rounds = [int(k) for k in re.findall(rf"robot {robot} round +(\d+)", text)]
    return max(rounds, default=-1)


def service_pids(run_dir: Path, service: str, robot: int | None = None) -> list[int]:
    """Pids of the run's processes of ``service`` (and ``--robot robot``), from /proc."""
    config = str(run_dir / "config.yaml")
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        if service in cmd and config in cmd and (robot is None or f"--robot\0{robot}" in "\0".join(cmd)):
            pids.append(int(proc.name))
    return pids


def kill_at_round(run_dir: Path, service: str, robot: int, round: int, timeout: float = 300, after_s: float = 0.0) -> int:
    """SIGKILL ``service`` ``robot`` of the run ``after_s`` seconds after its robot reported
    ``round`` (metrics come at checkpoint rounds: a delay kills it between checkpoints); its pid."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if reported_round(run_dir, robot) >= round and (pids := service_pids(run_dir, service, robot)):
            time.sleep(after_s)
            os.kill(pids[0], signal.SIGKILL)
            return pids[0]
        time.sleep(0.05)
    raise TimeoutError(f"{service} {robot} of {run_dir} never reported round {round}")


def leftovers(run_dir: Path) -> list[int]:
    """Processes of the run still alive (none should be, once ``up`` returned)."""
    return [p for s in ("router", "recorder", "observer", "world", "lidar", "learner") for p in service_pids(run_dir, s)]


def final_losses(run_dir: Path) -> dict[str, float]:
    summary = json.loads((run_dir / "summary.json").read_text())
    return {r: v["final_val_bce"] for r, v in summary["learners"].items()}
