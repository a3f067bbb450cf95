"""The launcher's end of a run: how long each service gets to finish by itself."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

from swarmmap.services.launcher import Child, Launcher, host_cores
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


def test_up_gives_learners_compute_slots_when_they_outnumber_the_cores(tmp_path):
    """More learner processes than this host's cores: ``up`` lets at most as many train at once
    as there are cores; fewer, in process, or a value the user set: left as it is."""
    cores = host_cores()
    many = Launcher(RunConfig(run_dir=tmp_path / "a", robots=cores + 1), threading.Event()).cfg.learner
    assert many.compute_slots == cores
    few = Launcher(RunConfig(run_dir=tmp_path / "b", robots=cores), threading.Event()).cfg.learner
    assert not few.compute_slots
    inproc = RunConfig.model_validate({"run_dir": str(tmp_path / "c"), "robots": cores + 1, "learner": {"transport": "inproc"}})
    assert not Launcher(inproc, threading.Event()).cfg.learner.compute_slots
    off = RunConfig.model_validate({"run_dir": str(tmp_path / "d"), "robots": cores + 1, "learner": {"compute_slots": 0}})
    assert Launcher(off, threading.Event()).cfg.learner.compute_slots == 0
