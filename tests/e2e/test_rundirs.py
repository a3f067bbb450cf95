"""Runs are never overwritten and never hang, with real runs: a run interrupted for real is
refused without ``--resume`` and resumed with it, its rows, first val_bce, wall time, logs and
recording kept; ``up`` twice on a finished run refuses the second; a run that makes no progress
ends by itself naming who holds it up; a disk that fills up under the run ends it within a
minute, naming the disk."""

from __future__ import annotations

import csv
import errno
import json
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.conftest import PROMPT_S, SWARMMAP, clean_env, wait_until
from tests.harness import reported_round

pytestmark = pytest.mark.e2e
SMOKE = ("--preset", "smoke", "--set", "observer.mc_samples=4")


def up(run_dir: Path, *extra: str, timeout: float = 300) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    proc = subprocess.run([*SWARMMAP, "up", *SMOKE, "--run-dir", str(run_dir), *extra], capture_output=True, text=True,
                          timeout=timeout, env=clean_env())
    return proc, time.monotonic() - t0


def background(run_dir: Path, out: Path, *extra: str) -> subprocess.Popen:
    """``up`` in the background, its console in ``out``."""
    with out.open("w") as f:
        return subprocess.Popen([*SWARMMAP, "up", *SMOKE, "--run-dir", str(run_dir), *extra], stdout=f, stderr=subprocess.STDOUT,
                                env=clean_env())


def files(run_dir: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}


def metric_keys(run_dir: Path) -> list[tuple[str, str, str]]:
    return [(r["robot"], r["round"], r["final"]) for r in csv.DictReader((run_dir / "metrics.csv").open())]


def test_an_interrupted_run_resumes_only_when_asked_and_up_twice_on_a_finished_one_refuses(tmp_path):
    """Ctrl-C in the middle of a run; ``up`` again is refused, naming --resume; ``up --resume``
    finishes it with every earlier row, first val_bce, log line and recording kept and no row
    twice; ``up`` (resumed or not) on the finished run is refused and changes nothing."""
    run, rounds = tmp_path / "run", ("--robots", "2", "--rounds", "30")
    proc = background(run, tmp_path / "first.log", *rounds)
    try:
        assert wait_until(lambda: min(reported_round(run, r) for r in range(2)) >= 5 or proc.poll() is not None, 240, 0.2)
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        assert proc.wait(120) == 130, (tmp_path / "first.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    first = json.loads((run / "summary.json").read_text())
    rows, logs = metric_keys(run), {p.name: p.read_text() for p in (run / "logs").glob("learner-*.log")}
    assert not first["ok"] and first["status"] == 130 and ("0", "30", "1") not in rows
    kept = files(run)
    refused, took = up(run, *rounds)
    assert refused.returncode == 2 and took < PROMPT_S
    assert f"{run} holds a run that did not finish (it was interrupted); resume it with --resume" in refused.stderr
    assert files(run) == kept
    resumed, _ = up(run, *rounds, "--resume")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    after, summary = metric_keys(run), json.loads((run / "summary.json").read_text())
    assert after[: len(rows)] == rows and len(after) == len(set(after)), "rows lost or written twice"
    assert sorted(k for k in after if k[2] == "1") == [("0", "30", "1"), ("1", "30", "1")]
    assert summary["ok"] and summary["run_id"] == first["run_id"] and summary["attempts"] == 2
    assert summary["started"] == first["started"] and summary["earlier_wall_time_s"] == first["wall_time_s"]
    assert summary["wall_time_s"] > first["wall_time_s"] + 5
    for robot, entry in summary["learners"].items():
        assert entry["first_val_bce"] == first["learners"][robot]["first_val_bce"]
    for name, text in logs.items():
        now = (run / "logs" / name).read_text()
        assert now.startswith(text) and "swarmmap up: run" in now[len(text):] and "resuming from" in now[len(text):]
    assert (run / "recording.rrd").read_bytes() == kept[run / "recording.rrd"] and (run / "recording-2.rrd").stat().st_size
    finished = files(run)
    for extra in ((), ("--resume",)):
        again, took = up(run, *rounds, *extra)
        assert again.returncode == 2 and took < PROMPT_S, again.stderr[-2000:]
        assert f"refusing to start: {run} holds a finished run (it ended " in again.stderr
        assert "never overwritten; choose another --run-dir, or move that one away" in again.stderr
    assert files(run) == finished, "the finished run's files were changed"


# A fault trial (a learner that stops answering), run with the others (make test-faults).
@pytest.mark.faults
def test_a_run_that_makes_no_progress_ends_by_itself_naming_who_holds_it_up(tmp_path):
    """Every message of Algorithm 1 lost and no neighbour ever left out: the learners wait
    forever, and the recorder ends the run once nothing came for recorder.stall_timeout_s."""
    run = tmp_path / "run"
    proc, took = up(run, "--rounds", "30", "--set", "faults.link_success=0.0001", "--set", "learner.silent_after_s=3600",
                    "--set", "recorder.stall_timeout_s=12", timeout=240)
    assert proc.returncode == 1, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["reason"].startswith("the run made no progress (no new Metrics, no scans) for 12 s (recorder.stall_timeout_s): ")
    assert summary["held_up_by"] and set(summary["held_up_by"]) <= {0, 1, 2}
    assert f"learner(s) {summary['held_up_by']}" in summary["reason"] and "the run made no progress" in proc.stderr


def fill(folder: Path) -> None:
    """Write a file in ``folder`` until its disk is full (unbuffered: nothing is left to flush, and
    fail again, when the file is closed)."""
    with (folder / "filler").open("wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * (1 << 16))
        except OSError as e:
            assert e.errno == errno.ENOSPC, e


def test_a_disk_that_fills_up_under_the_run_ends_it_within_a_minute_naming_the_disk(tmpfs, tmp_path):
    disk = tmpfs("64m")
    run = disk / "run"
    out = tmp_path / "up.log"
    proc = background(run, out, "--rounds", "400")
    try:
        assert wait_until(lambda: reported_round(run, 0) >= 5 or proc.poll() is not None, 240, 0.2), out.read_text()[-3000:]
        assert proc.poll() is None, out.read_text()[-3000:]
        fill(disk)
        filled = time.monotonic()
        code = proc.wait(90)
        took = time.monotonic() - filled
    finally:
        if proc.poll() is None:
            proc.kill()
    text = out.read_text()
    assert code == 1 and took < 60, f"status {code} after {took:.0f} s:\n{text[-3000:]}"
    assert f"the run failed (recorder status 1): the disk of the run directory is full (the disk of {run}: tmpfs mounted at {disk}" in text
