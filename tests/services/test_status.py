"""``swarmmap status``: a finished or missing run is answered at once from what it left; a run
whose router is gone is answered within seconds; Ctrl-C and SIGTERM end it at once. (A live
run: tests/e2e/test_up.py.)"""

from __future__ import annotations

import signal
import subprocess
import time

import pytest

from tests.conftest import PROMPT_S, SWARMMAP, clean_env, free_port, recorded_run, wait_until

pytestmark = pytest.mark.timeout(60)


def status(*args: str) -> tuple[subprocess.CompletedProcess, float]:
    start = time.monotonic()
    proc = subprocess.run([*SWARMMAP, "status", *args], capture_output=True, text=True, timeout=30, env=clean_env())
    return proc, time.monotonic() - start


@pytest.mark.integration
def test_a_finished_run_is_answered_from_its_summary_at_once(tmp_path):
    run_dir = recorded_run(tmp_path / "run", losses=(0.125, 0.250))
    proc, took = status(str(run_dir))
    assert proc.returncode == 0 and took < PROMPT_S
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("run demo-1 (smoke, fourier, procedural 2x2, 2 robots): not running; finished ok at ")
    assert "(all 2 learners finished)" in lines[0]
    assert lines[1:] == ["  learner   0  rounds    60  final val_bce 0.1250", "  learner   1  rounds    60  final val_bce 0.2500"]
    failed = recorded_run(tmp_path / "failed", ok=False)
    proc, _ = status("--config", str(failed / "config.yaml"))
    assert "finished failed at" in proc.stdout and "learner 1 left before finishing" in proc.stdout
    assert "(did not finish)" in proc.stdout


@pytest.mark.integration
def test_a_missing_run_is_answered_at_once(tmp_path):
    proc, took = status(str(tmp_path / "nothing"))
    assert proc.returncode == 1 and took < PROMPT_S and "holds no run" in proc.stdout


def stopped_run(tmp_path):
    """A run directory whose services are gone without a summary (killed): its router's port is free."""
    run_dir = recorded_run(tmp_path / "run")
    (run_dir / "summary.json").unlink()
    text = (run_dir / "config.yaml").read_text().replace("connect: []", f"connect:\n  - tcp/127.0.0.1:{free_port()}")
    text = text.replace("insecure: false", "insecure: true")  # a peer session: it opens, and finds nobody
    (run_dir / "config.yaml").write_text(text)
    return run_dir


@pytest.mark.integration
def test_a_run_that_stopped_without_a_summary_is_answered_within_seconds(tmp_path):
    proc, took = status(str(stopped_run(tmp_path)), "--window", "0.5")
    assert took < PROMPT_S and "not running" in proc.stdout, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.integration
def test_ctrl_c_and_sigterm_end_it_at_once(tmp_path, sig):
    run_dir = stopped_run(tmp_path)
    err = tmp_path / "status.err"
    with err.open("w") as f:
        proc = subprocess.Popen([*SWARMMAP, "status", str(run_dir), "--window", "30"], stdout=subprocess.DEVNULL,
                                stderr=f, text=True, env=clean_env())
    try:
        assert wait_until(lambda: "asking its services" in err.read_text(), 20), err.read_text()
        proc.send_signal(sig)
        start = time.monotonic()
        assert proc.wait(timeout=10) == 130
        assert time.monotonic() - start < 10
    finally:
        if proc.poll() is None:
            proc.kill()


def test_a_live_runs_learners_come_with_the_time_left_at_the_slowest_learners_pace():
    from swarmmap.services.status import Snapshot, live_report
    from swarmmap.shared.run.config import resolve
    from swarmmap.shared.wire.protocol import Metrics

    cfg = resolve({"preset": "smoke", "robots": 2, "run_id": "r", "learner": {"rounds": 60}}, environ={})
    snap = Snapshot()
    for robot, (rnd, wall) in enumerate([(20, 10.0), (30, 12.0)]):  # robot 0: 20 rounds in 10 s, 40 to go
        snap.metrics[robot] = Metrics(run="r", sender=robot, round=rnd, wall_time_s=wall, val_bce=0.3, consensus_error=0.0,
                                      bytes_sent=0, bytes_received=0, final=False)
    assert "learners (2 of 2 reported, of 60 rounds; ETA 20 s):" in live_report(cfg, snap, 1.0, None)
    for robot in (0, 1):
        snap.metrics[robot] = snap.metrics[robot].model_copy(update={"round": 60, "final": True})
    assert "learners (2 of 2 reported, of 60 rounds):" in live_report(cfg, snap, 1.0, None)
