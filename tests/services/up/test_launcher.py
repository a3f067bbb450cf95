"""The launcher's end of a run: how long each service gets to finish by itself."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import pytest

from swarmmap.services.up.launcher import Child, Launcher, host_cores
from swarmmap.shared.run.config import RunConfig, UpSettings


def sleeper(seconds: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", f"import time; time.sleep({seconds})"])


@pytest.mark.integration
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
        launcher.let_leave(lambda: {"world-0", "learner-0"})
        took = time.monotonic() - start
        assert learner.proc.poll() == 0, "up stopped waiting before the learner had finished"
        assert world.proc.poll() is None, "the world was waited for as long as a learner"
        assert took < 15, f"let_leave took {took:.1f} s: it waited past the learner's exit"
    finally:
        for c in (world, learner):
            c.proc.kill()
            c.proc.wait()


@pytest.mark.integration
def test_a_restarted_service_not_up_again_when_the_run_ends_gets_no_grace(tmp_path):
    """A learner restarted just before the run ended, still starting (no liveliness token), will
    never hear ``run/done`` (the recorder has gone): ``up`` does not wait for it, while a restarted
    learner that is up gets its grace."""
    cfg = RunConfig(run_dir=tmp_path / "run", up=UpSettings(stop_grace_s=0.3, learner_grace_s=20.0))
    launcher = Launcher(cfg, threading.Event())
    starting = Child("learner", 1, sleeper(60), tmp_path / "learner-1.log", restarts=1)
    finishing = Child("learner", 2, sleeper(2.0), tmp_path / "learner-2.log", restarts=1)
    launcher.children = [starting, finishing]
    try:
        start = time.monotonic()
        launcher.let_leave(lambda: {"learner-2"})
        took = time.monotonic() - start
        assert finishing.proc.poll() == 0, "up stopped waiting before the restarted learner that is up had finished"
        assert starting.proc.poll() is None and took < 15, f"up waited {took:.1f} s for a learner that never came up again"
    finally:
        for c in (starting, finishing):
            c.proc.kill()
            c.proc.wait()


@pytest.mark.integration
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


def service(tmp_path, name: str, code: str) -> Child:
    """A real process standing in for one service, its output in its log as up keeps it."""
    log_path = tmp_path / f"{name}.log"
    with log_path.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=out, stderr=subprocess.STDOUT)
    service_name, ident = name.rsplit("-", 1)
    return Child(service_name, int(ident), proc, log_path)


@pytest.mark.integration
def test_a_service_that_refuses_its_settings_ends_the_run_at_once_with_its_reason_in_the_summary(tmp_path):
    """Status 2 is a refusal that would only repeat: ``up`` stops waiting for the recorder at
    once (not after FAILURE_GRACE_S) and summary.json says which service refused and why."""
    cfg = RunConfig(run_dir=tmp_path / "run", up=UpSettings(stop_grace_s=2.0))
    launcher = Launcher(cfg, threading.Event())
    launcher.run_dir.mkdir()
    recorder = service(tmp_path, "recorder-0", "import time; time.sleep(120)")
    world = service(tmp_path, "world-0", "import sys; print('2030-01-01 10:00:00,000 ERROR world: floor plan refused: "
                                         "plan.svg: file does not exist'); sys.exit(2)")
    launcher.children = [recorder, world]
    try:
        start = time.monotonic()
        status = launcher.watch(recorder)
        took = time.monotonic() - start
        assert status == 1 and took < 10, f"watch returned {status} after {took:.1f} s"
        launcher.shutdown()
        launcher.complete_summary(took, status)
    finally:
        for c in (recorder, world):
            if c.proc.poll() is None:
                c.proc.kill()
                c.proc.wait()
    summary = json.loads((launcher.run_dir / "summary.json").read_text())
    assert not summary["ok"] and summary["status"] == 1
    assert summary["reason"] == "world-0 refused to run (exit status 2): floor plan refused: plan.svg: file does not exist"
    assert summary["services"]["world-0"]["exit_code"] == 2 and summary["services"]["world-0"]["restarts"] == 0


def test_the_reason_is_the_services_last_error_without_time_stamps():
    from swarmmap.services.up.launcher import last_error

    record = ["2030-01-01 10:00:00,000 INFO learner: robot 1: 900 points",
              "2030-01-01 10:00:01,000 ERROR learner: robot 1: cannot read checkpoint c/robot-1.pt: load failed.",
              "Details on a second line", "2030-01-01 10:00:02,000 INFO learner: stopped"]
    assert last_error(record) == "robot 1: cannot read checkpoint c/robot-1.pt: load failed. Details on a second line"
    refused = ["config error:", "  zenoh.secrets: learner-0 has no credentials in s", "  create them with swarmmap secrets"]
    assert last_error(refused) == "config error: zenoh.secrets: learner-0 has no credentials in s create them with swarmmap secrets"
    crash = ["Traceback (most recent call last):", '  File "x.py", line 1, in <module>', "ValueError: bad value", ""]
    assert last_error(crash) == "ValueError: bad value"


def test_a_run_directory_is_never_overwritten_and_resumed_only_when_asked(tmp_path):
    """A finished run is refused, resumed or not; one that did not finish is refused without
    ``--resume`` (naming it) and with other settings; a new directory takes any run."""
    from swarmmap.services.up.launcher import prepare, run_dir_problem, write_config
    from swarmmap.shared.run.config import resolve
    from tests.conftest import recorded_run

    def cfg(run_dir, **cli):
        return prepare(resolve({"run_dir": str(run_dir), "zenoh": {"insecure": True}, **cli}, preset="smoke", environ={}))

    assert run_dir_problem(cfg(tmp_path / "new")) is None and run_dir_problem(cfg(tmp_path / "new", up={"resume": True})) is None
    done = recorded_run(tmp_path / "done")
    for resume in (False, True):
        why = run_dir_problem(cfg(done, up={"resume": resume}))
        assert why.startswith(f"{done} holds a finished run (it ended ") and "never overwritten; choose another --run-dir" in why
    stopped = tmp_path / "stopped"
    write_config(cfg(stopped, run_id="first"))  # what prepare leaves, or a run stopped before its summary
    why = run_dir_problem(cfg(stopped))
    assert why == (f"{stopped} holds a run that did not finish (no summary: it is still running, or it stopped without one); "
                   f"resume it with --resume, or choose another --run-dir")
    assert run_dir_problem(cfg(stopped, up={"resume": True})) is None
    assert "(seed 0 there, 3 here)" in run_dir_problem(cfg(stopped, seed=3, up={"resume": True}))
    assert cfg(stopped, up={"resume": True}).run_id == "first", "a resumed run keeps its run id"
    (stopped / "summary.json").write_text(json.dumps({"ok": False, "status": 130}))
    assert "(it was interrupted)" in run_dir_problem(cfg(stopped))
    exploring = cfg(stopped, explore={"policy": "frontier"}, up={"resume": True})  # (its drive is not checkpointed)
    assert "an exploration cannot be resumed (the drive" in run_dir_problem(exploring)


def test_resume_names_the_run_it_resumes():
    import pytest

    from swarmmap.services.up.launcher import prepare
    from swarmmap.shared.run.config import ConfigError, resolve

    with pytest.raises(ConfigError, match="up.resume: name the run to resume: --run-dir RUN_DIR"):
        prepare(resolve({"up": {"resume": True}}, preset="smoke", environ={}))
