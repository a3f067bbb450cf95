"""End to end without a launcher: every service started on its own, as compose and SLURM start
them (settings from the environment alone, credentials from `swarmmap secrets`, any start
order). The run ends by itself: every
service exits once the recorder says the run is over, the run directory is whole and the
recording shows every robot; a killed learner ends the run with a failure that names it."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest

from tests.conftest import SWARMMAP, clean_env, free_port, recording_entities, wait_until

pytestmark = pytest.mark.e2e

ROBOTS = 2


def start_team(run_dir: Path, run_id: str, rounds: int, **settings: str) -> dict[str, subprocess.Popen]:
    """router, world, observer, lidars, learners and recorder, each its own process (world first:
    it waits for the others); ``settings`` as environment variables (``SWARMMAP_...``)."""
    port = free_port()
    env = clean_env() | {
        "SWARMMAP_RUN_ID": run_id, "SWARMMAP_PRESET": "smoke", "SWARMMAP_ROBOTS": str(ROBOTS),
        "SWARMMAP_RUN_DIR": str(run_dir), "SWARMMAP_LEARNER__ROUNDS": str(rounds),
        "SWARMMAP_ZENOH__MODE": "peer", "SWARMMAP_ZENOH__CONNECT": f"[tcp/127.0.0.1:{port}]",
        "SWARMMAP_ZENOH__LISTEN": "[tcp/127.0.0.1:0]", "SWARMMAP_ZENOH__MULTICAST_SCOUTING": "false",
        "SWARMMAP_WORLD__WAIT_FOR": "[lidar, learner, recorder, observer]",
    } | settings
    (run_dir / "logs").mkdir(parents=True)
    # The run's credentials first (compose and SLURM do the same): every link is then mutual TLS.
    subprocess.run([*SWARMMAP, "secrets"], env=env, check=True, capture_output=True, timeout=60)
    commands = {"router-0": ["router", "--zenoh-mode", "router", "--zenoh-listen", f"tcp/127.0.0.1:{port}",
                             "--set", "zenoh.connect=[]"],
                "world-0": ["world"],
                "observer-0": ["observer", "--set", f"observer.save={run_dir / 'recording.rrd'}"]}
    for i in range(ROBOTS):
        commands[f"lidar-{i}"] = ["lidar", "--robot", str(i)]
        commands[f"learner-{i}"] = ["learner", "--robot", str(i)]
    commands["recorder-0"] = ["recorder"]
    procs = {}
    for name, args in commands.items():
        with (run_dir / "logs" / f"{name}.log").open("w") as log:
            procs[name] = subprocess.Popen([*SWARMMAP, *args], stdout=log, stderr=subprocess.STDOUT, env=env)
    return procs


def wait_all(procs: dict[str, subprocess.Popen], timeout: float) -> dict[str, int | None]:
    wait_until(lambda: all(p.poll() is not None for p in procs.values()), timeout, interval=0.2)
    codes = {name: p.poll() for name, p in procs.items()}
    for p in procs.values():
        if p.poll() is None:
            p.kill()
            p.wait()
    return codes


def logs(run_dir: Path) -> str:
    return "\n".join(f"--- {f.name}\n{f.read_text()[-1500:]}" for f in sorted((run_dir / "logs").glob("*.log")))


def test_services_started_alone_finish_by_themselves_with_a_whole_run_directory(tmp_path, run_id):
    run_dir = tmp_path / "run"
    procs = start_team(run_dir, run_id, rounds=20)
    codes = wait_all(procs, timeout=240)
    assert all(code == 0 for code in codes.values()), f"{codes}\n{logs(run_dir)}"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["reason"] == f"all {ROBOTS} learners finished"
    for robot in map(str, range(ROBOTS)):
        entry = summary["learners"][robot]
        assert entry["finished"] and entry["rounds"] == 20 and entry["final_val_bce"] < entry["first_val_bce"]
    for name in ("config.yaml", "metrics.csv", "groundtruth.png", "groundtruth.npz", "observer.json"):
        assert (run_dir / name).stat().st_size > 0, name
    assert "robots: 2" in (run_dir / "config.yaml").read_text()
    rows = (run_dir / "metrics.csv").read_text().splitlines()
    assert len(rows) == 1 + ROBOTS * 5  # rounds 0, 5, 10, 15, 20
    entities = recording_entities(run_dir / "recording.rrd")
    for robot in range(ROBOTS):
        # The world waited for the observer, so the recording holds the whole traversal.
        assert {f"/world/robots/{robot}/pose", f"/world/robots/{robot}/trajectory", f"/maps/mean/robot-{robot}"} <= entities.keys()
    report = json.loads((run_dir / "observer.json").read_text())
    assert report["last_round_mapped"] == {str(r): 20 for r in range(ROBOTS)}


def test_a_killed_learner_ends_the_run_with_a_failure_naming_it(tmp_path, run_id):
    run_dir = tmp_path / "run"
    # A learner that left may come back within recorder.rejoin_timeout_s (20 s by default): 5 s here.
    procs = start_team(run_dir, run_id, rounds=100000, SWARMMAP_RECORDER__REJOIN_TIMEOUT_S="5")
    try:
        assert wait_until(lambda: "round    5" in (run_dir / "logs" / "recorder-0.log").read_text(), 180, 0.2), logs(run_dir)
        procs["learner-1"].send_signal(signal.SIGKILL)
        codes = wait_all(procs, timeout=60)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
    assert None not in codes.values(), f"left running a minute after the kill: {codes}"
    assert codes["recorder-0"] == 1
    summary = json.loads((run_dir / "summary.json").read_text())
    assert not summary["ok"] and "learner 1" in summary["reason"]
    assert "run FAILED: learner 1 left before finishing" in (run_dir / "logs" / "recorder-0.log").read_text()
    assert all(codes[name] == 0 for name in ("world-0", "lidar-0", "lidar-1", "observer-0", "router-0")), codes
