"""The launcher's end of a run: how long each service gets to finish by itself."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

from swarmmap.services.launcher import Child, Launcher
from swarmmap.shared.config import RunConfig, UpSettings


def sleeper(seconds: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", f"import time; time.sleep({seconds})"])


def test_a_learner_gets_its_own_grace_to_write_its_outputs(tmp_path):
    """Once the run is over a learner may still be writing its model and maps: ``up`` waits up
    to ``learner_grace_s`` for it, while the other services get only ``stop_grace_s``."""
    cfg = RunConfig(run_dir=tmp_path / "run", up=UpSettings(stop_grace_s=0.3, learner_grace_s=20.0))
    launcher = Launcher(cfg, threading.Event())
    world = Child("world", 0, sleeper(60), tmp_path / "world.log")
    learner = Child("learner", 0, sleeper(2.0), tmp_path / "learner.log")
    launcher.children = [world, learner]
    try:
        start = time.monotonic()
        launcher.let_leave()
        took = time.monotonic() - start
        assert learner.proc.poll() == 0, "up stopped waiting before the learner had finished"
        assert world.proc.poll() is None, "the world was waited for as long as a learner"
        assert took < 15, f"let_leave took {took:.1f} s: it waited past the learner's exit"
    finally:
        for c in (world, learner):
            c.proc.kill()
            c.proc.wait()
