"""End to end: ``swarmmap up`` launches every service as its own process on loopback and
leaves a complete run directory (with ``--mcap``, a rosbag2 in MCAP read back with rosbags);
``status`` sees the live services; Ctrl-C stops everything."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from swarmmap.services.world.simulation import build_plan
from swarmmap.shared.learning.models import predict
from swarmmap.shared.learning.networks import load_model
from swarmmap.shared.run.config import RunConfig
from tests.conftest import PROMPT_S, SWARMMAP, clean_env, wait_until
from tests.e2e.mapcheck import observed_agreement

pytestmark = pytest.mark.e2e



@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("smoke") / "run"
    proc = subprocess.run([*SWARMMAP, "up", "--robots", "3", "--rounds", "20", "--preset", "smoke", "--mcap",
                           "--set", "observer.map_resolution_m=0.05", "--run-dir", str(run_dir)],
                          capture_output=True, text=True, timeout=300, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir, proc


def test_every_learner_ran_as_its_own_process(smoke_run):
    run_dir, _ = smoke_run
    summary = json.loads((run_dir / "summary.json").read_text())
    learners = summary["learners"]
    assert sorted(learners) == ["0", "1", "2"]
    pids = {v["pid"] for v in learners.values()}
    assert len(pids) == 3 and os.getpid() not in pids
    for v in learners.values():
        assert v["reported_pid"] == v["pid"], "the Metrics did not come from the launched process"
        assert v["exit_code"] == 0 and v["finished"] and v["rounds"] == 20
    assert {"router-0", "world-0", "lidar-0", "lidar-1", "lidar-2"} <= summary["services"].keys()
    assert len({s["pid"] for s in summary["services"].values()}) == len(summary["services"])


def test_validation_loss_fell_for_every_robot(smoke_run):
    run_dir, _ = smoke_run
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))
    assert {"robot", "round", "wall_time_s", "val_bce", "consensus_error", "bytes_sent",
            "bytes_received"} <= rows[0].keys()
    for robot in "012":
        mine = sorted((r for r in rows if r["robot"] == robot), key=lambda r: int(r["round"]))
        assert [int(r["round"]) for r in mine] == [0, 5, 10, 15, 20]
        assert float(mine[-1]["val_bce"]) < float(mine[0]["val_bce"])
        assert int(mine[-1]["bytes_sent"]) > 0 and int(mine[-1]["bytes_received"]) > 0
    summary = json.loads((run_dir / "summary.json").read_text())
    for v in summary["learners"].values():
        assert v["final_val_bce"] < v["first_val_bce"]


def test_run_directory_is_complete_and_maps_show_the_plan(smoke_run):
    run_dir, _ = smoke_run
    cfg = RunConfig.model_validate(yaml.safe_load((run_dir / "config.yaml").read_text()))
    assert cfg.robots == 3 and cfg.learner.rounds == 20 and cfg.preset == "smoke"
    assert Image.open(run_dir / "groundtruth.png").mode == "L"
    plan = build_plan(cfg)
    room_points = np.array([r.representative_point().coords[0] for r in plan.rooms])
    for robot in range(3):
        img = np.asarray(Image.open(run_dir / "maps" / f"robot-{robot}-mean.png"))
        assert img.ndim == 2 and img.size > 100
        assert (run_dir / "data" / f"robot-{robot}.npz").exists()
        model = load_model(run_dir / "models" / f"robot-{robot}.pt")
        assert (predict(model, room_points) < 0.5).mean() >= 0.8, "rooms should read free"
        assert observed_agreement(run_dir, robot) > 0.8


def test_a_smoke_run_leaves_an_overview_and_ros_maps_at_the_ground_truths_resolution(smoke_run):
    run_dir, _ = smoke_run
    assert Image.open(run_dir / "overview.png").format == "PNG"
    truth = np.load(run_dir / "groundtruth.npz")["grid"]
    for robot in range(3):
        assert np.load(run_dir / "maps" / f"robot-{robot}.npz")["mean"].shape == truth.shape
        ros = yaml.safe_load((run_dir / "maps" / f"robot-{robot}.yaml").read_text())
        assert Image.open(run_dir / "maps" / ros["image"]).size == truth.shape[::-1]


def test_the_console_ends_with_where_everything_went_and_what_to_run_next(smoke_run):
    """Phases on the console, then the closing block: each robot's final val_bce as in the
    summary, the team's mean, the run directory and the commands to copy."""
    run_dir, proc = smoke_run
    for phase in ("plan procedural-2x2-seed0 (procedural)", "starting 10 services", "traversal done:",
                  "training: 3 learner(s), 20 rounds", "training: round 20 of 20 (100%)"):
        assert phase in proc.stderr, phase
    summary = json.loads((run_dir / "summary.json").read_text())
    finals = [summary["learners"][r]["final_val_bce"] for r in "012"]
    block = proc.stdout[proc.stdout.index(f"run {summary['run_id']}: ok"):]
    assert "  final val_bce  " + "  ".join(f"robot {r} {v:.4f}" for r, v in enumerate(finals)) in block
    assert f"team mean      {sum(finals) / 3:.4f} over 3 robot(s)" in block and f"run directory  {run_dir}" in block
    assert f"rerun {run_dir / 'recording.rrd'}" in block and f"swarmmap experiment score {run_dir} --ensemble" in block
    recorder = (run_dir / "logs" / "recorder-0.log").read_text()
    for phase in ("every learner is alive (3)", "traversal done:", "training: round 20 of 20", "final val_bce: robot 0"):
        assert phase in recorder, phase


def test_a_runs_bag_holds_every_topic_it_lists_and_the_final_maps(smoke_run):
    from rosbags.highlevel import AnyReader

    run_dir, _ = smoke_run
    observer = json.loads((run_dir / "observer.json").read_text())
    listed = observer["mcap"]["messages"]
    with AnyReader([run_dir / "bag"]) as reader:
        assert {c.topic for c in reader.connections} == set(listed)
        got: dict[str, list] = {}
        for conn, _, raw in reader.messages():
            got.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    assert {t: len(v) for t, v in got.items()} == listed
    for robot in range(3):
        assert len(got[f"/robot_{robot}/scan"]) > 10 and len(got[f"/robot_{robot}/map"]) >= 4  # every evaluation
        final = got[f"/robot_{robot}/map"][-1]
        with np.load(run_dir / "maps" / f"robot-{robot}.npz") as saved:  # the learner's own final map, same cells
            mean = saved["mean"]
            assert (final.info.height, final.info.width) == mean.shape
            assert (final.info.origin.position.x, final.info.origin.position.y) == pytest.approx(tuple(saved["origin"]))
        assert np.abs(final.data.reshape(mean.shape) / 100 - mean).mean() < 0.01
    assert "/robot_0/map_std" not in got  # a FourierNet has no std
    assert got["/reference"][0].info.width == got["/robot_0/map"][0].info.width
    assert {t.child_frame_id for m in got["/tf"] for t in m.transforms} == {f"robot_{i}/base_scan" for i in range(3)}


def test_the_run_tools_answer_for_a_finished_run_in_seconds(smoke_run, tmp_path):
    run_dir, _ = smoke_run
    start = time.monotonic()
    status = subprocess.run([*SWARMMAP, "status", str(run_dir)], capture_output=True, text=True, timeout=30, env=clean_env())
    assert status.returncode == 0 and time.monotonic() - start < PROMPT_S
    assert "not running; finished ok at" in status.stdout and status.stdout.count("final val_bce") == 3
    runs = subprocess.run([*SWARMMAP, "runs", str(run_dir.parent)], capture_output=True, text=True, timeout=30, env=clean_env())
    row = next(line.split() for line in runs.stdout.splitlines()[1:] if line.split()[0] == run_dir.name)
    assert row[1:4] == ["ok", "3", "20"]
    logs = subprocess.run([*SWARMMAP, "logs", str(run_dir), "world-0"], capture_output=True, text=True, timeout=30, env=clean_env())
    assert logs.returncode == 0 and "traversal done" in logs.stdout
    out = tmp_path / "curves.png"
    cmp = subprocess.run([*SWARMMAP, "compare", str(run_dir), "--out", str(out)], capture_output=True, text=True, timeout=60,
                         env=clean_env())
    assert cmp.returncode == 0 and out.stat().st_size > 0 and "final mean val_bce" in cmp.stdout


def metric_rows(run_dir: Path) -> list[dict]:
    """The complete rows of metrics.csv (the file may be mid-write while the run goes on)."""
    path = run_dir / "metrics.csv"
    if not path.exists():
        return []
    lines = path.read_text().splitlines(keepends=True)
    complete = [line for line in lines if line.endswith("\n")]
    return list(csv.DictReader(complete))


def start_up(run_dir: Path, rounds: int) -> subprocess.Popen:
    return subprocess.Popen([*SWARMMAP, "up", "--preset", "smoke", "--rounds", str(rounds), "--run-dir",
                             str(run_dir)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=clean_env())


def test_status_lists_live_services_and_ctrl_c_stops_everything(tmp_path):
    run_dir = tmp_path / "run"
    proc = start_up(run_dir, rounds=100000)
    try:
        out = {"text": ""}

        def status_shows_learners() -> bool:
            if not (run_dir / "config.yaml").exists():
                return False
            res = subprocess.run([*SWARMMAP, "status", str(run_dir), "--window", "1"],
                                 capture_output=True, text=True, timeout=60, env=clean_env())
            out["text"] = res.stdout
            # the exchange's rates: a status tool receives no State (the access policy), each round's RoundComplete
            return all(f"learner    {i}" in res.stdout for i in range(3)) and "round-complete" in res.stdout and \
                all(re.search(rf"learner +{i} +round +\d+ +val_bce \d", res.stdout) for i in range(3))

        assert wait_until(status_shows_learners, 120, interval=0.5), out["text"]
        assert "lidar" in out["text"] and "router" in out["text"] and "world" in out["text"]
        lines = out["text"].splitlines()
        listed = lines[1:next(i for i, line in enumerate(lines) if line.startswith("learners"))]
        assert f"{len(listed)} service(s) alive" in lines[0], out["text"]
        # A State travels before the round's Metrics are recorded: interrupt once rows are on disk.
        assert wait_until(lambda: metric_rows(run_dir), 120, interval=0.5), "no Metrics were recorded"
        before = metric_rows(run_dir)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 130
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    for name, service in summary["services"].items():
        assert service["exit_code"] is not None, f"{name} was left running"
        with pytest.raises(ProcessLookupError):
            os.kill(service["pid"], 0)
    after = metric_rows(run_dir)
    assert after[: len(before)] == before, "metrics written before the interrupt were lost"
