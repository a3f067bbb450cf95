"""The Rerun observer: real learner States over Zenoh become mean and std map entities in an
.rrd that Rerun's own reader finds; the newest State of each learner is the one mapped; its
web viewer and gRPC server listen on loopback unless told otherwise."""

from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from swarmmap.services.observer import Observer, blueprint, open_sinks
from swarmmap.shared.run.config import resolve
from swarmmap.shared.wire.protocol import State, Tensor
from tests.conftest import SWARMMAP, clean_env, free_port, recording_entities, wait_until


def state(robot: int, rnd: int) -> State:
    return State(run="r", sender=robot, round=rnd, params=Tensor.of(np.zeros(3, np.float32), "<f4"))


def test_keeps_only_the_newest_state_of_each_learner():
    obs = Observer(resolve(preset="smoke", environ={}, cli={"observer": {"map_every": 1}}), rec=None, device=None)
    for rnd in (0, 1, 2):
        obs.on_state(state(0, rnd))
    obs.on_state(state(1, 5))
    obs.on_state(state(0, 1))  # late: older than the one waiting
    assert {r: m.round for r, m in obs.newest.items()} == {0: 2, 1: 5}
    assert obs.skipped == 2 and obs.states_in == 5
    obs.mapped_round[1] = 5
    del obs.newest[1]
    obs.on_state(state(1, 5))  # a duplicate of what was mapped
    assert 1 not in obs.newest


def test_maps_only_every_map_every_rounds_and_the_final_one():
    cfg = resolve(preset="smoke", environ={}, cli={"observer": {"map_every": 5}, "learner": {"rounds": 12}})
    obs = Observer(cfg, rec=None, device=None)
    for rnd in range(13):
        obs.on_state(state(0, rnd))
        if rnd in (5, 10, 12):
            assert obs.newest[0].round == rnd
        if rnd == 0:
            assert obs.newest[0].round == 0
    assert obs.states_in == 4  # rounds 0, 5, 10 and the final 12


@pytest.mark.e2e
def test_up_records_every_learners_mean_and_std_maps(tmp_path):
    run_dir = tmp_path / "run"
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--robots", "2", "--rounds", "10", "--model", "bnn",
                           "--run-dir", str(run_dir), "--set", "observer.mc_samples=10"],
                          capture_output=True, text=True, timeout=300, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    reader = RrdReader(run_dir / "recording.rrd")
    assert reader.recordings() and reader.blueprints(), "no recording or no blueprint in the .rrd"
    timelines = recording_entities(run_dir / "recording.rrd")
    for robot in (0, 1):
        for entity in (f"/maps/mean/robot-{robot}", f"/maps/std/robot-{robot}", f"/curves/val_bce/robot-{robot}",
                       f"/world/robots/{robot}/pose"):
            assert entity in timelines, f"{entity} missing; the recording has {sorted(timelines)}"
        assert "round" in timelines[f"/maps/std/robot-{robot}"]
    assert "/world/plan" in timelines
    report = json.loads((run_dir / "observer.json").read_text())
    assert report["last_round_mapped"] == {"0": 10, "1": 10}, "the final States were not mapped"
    assert report["maps"] >= 2 and report["map_time_mean_s"] > 0


@pytest.mark.integration
def test_observer_without_a_sink_is_refused(tmp_path):
    proc = subprocess.run([*SWARMMAP, "observer", "--preset", "smoke", "--set", "observer.save=null"],
                          capture_output=True, text=True, timeout=60, env=clean_env())
    assert proc.returncode == 2
    assert "observer: no sink" in proc.stderr


def listening_addresses(port: int) -> set[str]:
    """The local addresses that listen on TCP ``port`` on this machine (from /proc/net)."""
    found = set()
    for table, family in (("/proc/net/tcp", socket.AF_INET), ("/proc/net/tcp6", socket.AF_INET6)):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            address, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                raw = bytes.fromhex(address)
                raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))  # each 32-bit word is little-endian
                found.add(socket.inet_ntop(family, raw))
    return found


@pytest.mark.timeout(120)
@pytest.mark.parametrize("bind, expected", [(None, {"127.0.0.1"}), ("0.0.0.0", {"0.0.0.0"})])
@pytest.mark.integration
def test_the_web_viewer_and_its_grpc_server_listen_on_loopback_unless_told_otherwise(tmp_path, caplog, bind, expected):
    web, grpc = free_port(), free_port()
    settings = {"serve_web": True, "web_port": web, "grpc_port": grpc} | ({"bind": bind} if bind else {})
    cfg = resolve({"preset": "smoke", "observer": settings}, environ={})
    rec = rr.RecordingStream("swarmmap-test", recording_id="ports")
    names, servers = open_sinks(cfg, rec, blueprint(2, False))
    try:
        assert wait_until(lambda: listening_addresses(web) and listening_addresses(grpc), 60, 0.2), names
        assert listening_addresses(web) == expected and listening_addresses(grpc) == expected
    finally:
        rec.disconnect()
        for proc in servers:
            proc.terminate()
            proc.wait(30)
    # Stopped, the web viewer's server is gone: nothing of it keeps the port (or outlives the observer).
    assert wait_until(lambda: not listening_addresses(web), 10, 0.2), f"port {web} still served after the stop"
    warned = [r.getMessage() for r in caplog.records if "listen beyond loopback" in r.getMessage()]
    assert bool(warned) == (bind is not None), warned


def test_a_trajectory_is_logged_in_pieces_that_stay_bounded():
    """Each scan logs at most one piece of ``piece`` points, so the recording grows with the path
    (10,000 poses: at most 1 M points logged, where the whole path at every scan was 50 M); the
    pieces together are the path, and a robot that stands still adds nothing."""
    from swarmmap.services.observer import Trajectory

    path, logged, pieces = Trajectory(min_step=0.05, piece=100), 0, []
    for k in range(10_000):
        changed, finished = path.add(0.1 * k, 0.0)
        assert changed and len(path.points) <= 100
        logged += len(path.points)
        if finished is not None:
            pieces.append(finished)
    assert logged <= 10_000 * 100 and path.done == len(pieces) == 100
    drawn = [p for piece in pieces for p in piece[:-1]] + path.points
    assert [x for x, _ in drawn] == [0.1 * k for k in range(10_000)]
    assert path.add(999.9 + 0.01, 0.0) == (False, None)


def test_the_worlds_unknown_cells_reach_the_sinks_as_unknown_at_the_observers_resolution():
    """A dataset's reference (0 free, 1 occupied, 2 unknown at 0.05 m) resampled to the observer's
    0.1 m cells: the unknown stays unknown (a rosbag2's ``/reference`` holds -1 there, not a wall)."""
    import torch

    from swarmmap.shared.wire.protocol import WorldMap

    class Sink:
        def world(self, resolution, origin, shape, reference):
            self.got = (resolution, shape, reference)

    grid = np.full((40, 60), 2, np.uint8)
    grid[10:30, 10:50] = 0
    grid[10, 10:50] = 1
    cfg = resolve(preset="smoke", environ={}, cli={"observer": {"map_resolution_m": 0.1}})
    sink = Sink()
    obs = Observer(cfg, rec=rr.RecordingStream("test-observer"), device=torch.device("cpu"), sinks=[sink])
    obs.on_world(WorldMap(run="r", sender=0, resolution=0.05, origin=[-1.0, -1.0], grid=Tensor.of(grid, "|u1"),
                          val_points=Tensor.of(np.zeros((1, 2), np.float32), "<f4"),
                          val_labels=Tensor.of(np.zeros(1, np.float32), "<f4"), robots=1))
    resolution, shape, trinary = sink.got
    assert resolution == 0.1 and shape == (20, 30) and trinary.shape == shape
    assert (trinary[:5] == 2).all() and (trinary[15:] == 2).all()  # nobody saw there
    assert (trinary[6:14, 6:24] == 0).all() and (trinary[5, 6:24] == 1).all()
