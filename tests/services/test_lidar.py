"""A LiDAR streamer under a flood of scans: a real ``swarmmap lidar`` process, scans published
to it over Zenoh faster than it can turn them into points. Its memory stays bounded (at most a
few scans wait; the publisher is held back instead) and it serves every scan, none dropped."""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

from swarmmap.shared.run.config import ZenohSettings
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.protocol import Keys, Scan, Tensor
from tests.conftest import SWARMMAP, clean_env, free_port, wait_until

BEAMS, SCANS = 4096, 2000  # 37 kB a scan, 74 MB in all (an unbounded inbox grew by 91 MB here, a bounded one by 22)


def peak_rss_mb(pid: int) -> tuple[float, float]:
    """(resident now, peak resident) of process ``pid`` in MB."""
    status = open(f"/proc/{pid}/status").read()
    rss, hwm = (int(re.search(rf"{name}:\s+(\d+) kB", status).group(1)) / 1024 for name in ("VmRSS", "VmHWM"))
    return rss, hwm


@pytest.mark.timeout(180)
@pytest.mark.integration
def test_a_flood_of_scans_is_held_back_not_buffered_and_every_scan_is_served(tmp_path, run_id):
    port = free_port()
    log_path = tmp_path / "lidar.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen([*SWARMMAP, "lidar", "--preset", "smoke", "--set", "lidar.samples_per_beam=1", "--robot", "0",
                                 "--run-id", run_id, "--zenoh-insecure",
                                 "--zenoh-mode", "peer", "--zenoh-listen", f"tcp/127.0.0.1:{port}", "--no-zenoh-multicast-scouting"],
                                stdout=log, stderr=subprocess.STDOUT, env=clean_env())
    zenoh = ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], listen=["tcp/127.0.0.1:0"], multicast_scouting=False,
                          insecure=True)
    angles = np.linspace(-np.pi, np.pi, BEAMS, endpoint=False).astype(np.float32)
    try:
        with Bus.open(zenoh, Keys("swarmmap", run_id), "world", 0) as bus:
            assert not bus.wait_alive("lidar", {"0"}, 60), log_path.read_text()[-2000:]
            before, _ = peak_rss_mb(proc.pid)
            pub = bus.publisher(bus.keys.scan(0))
            for seq in range(SCANS):  # as fast as the streamer lets it: its inbox holds the publisher back when full
                pub.put(Scan(run=run_id, sender=0, seq=seq, t=0.2 * seq, pose=[0.0, 0.0, 0.0], max_range=3.5,
                             angles=Tensor.of(angles, "<f4"), ranges=Tensor.of(np.full(BEAMS, 2.0, np.float32), "<f4"),
                             hit=Tensor.of(np.ones(BEAMS, np.uint8), "|u1"), last=seq == SCANS - 1))
            done = wait_until(lambda: "traversal done" in log_path.read_text(), 120, interval=0.2)
            assert done, log_path.read_text()[-2000:]
            _, peak = peak_rss_mb(proc.pid)
    finally:
        proc.terminate()
        proc.wait(30)
    assert f"robot 0 traversal done: {SCANS} scans" in log_path.read_text(), "scans were dropped"
    assert peak - before < 45, f"the streamer grew by {peak - before:.0f} MB while {SCANS * BEAMS * 9 / 1e6:.0f} MB of scans came"


@pytest.mark.timeout(180)
@pytest.mark.integration
def test_points_of_scans_that_come_before_the_learners_subscription_is_known_are_held_not_lost(tmp_path, run_id):
    """A learner's subscription can reach the streamer after the world has started driving: the
    samples of the first scans wait for it (Zenoh drops what no known subscriber matches). Here
    the learner subscribes only after ten scans were served: it still gets all twenty."""
    from swarmmap.shared.wire.protocol import Samples

    port = free_port()
    log_path = tmp_path / "lidar.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen([*SWARMMAP, "lidar", "--preset", "smoke", "--robot", "0", "--run-id", run_id, "--zenoh-insecure",
                                 "--zenoh-mode", "peer", "--zenoh-listen", f"tcp/127.0.0.1:{port}", "--no-zenoh-multicast-scouting"],
                                stdout=log, stderr=subprocess.STDOUT, env=clean_env())
    zenoh = ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], listen=["tcp/127.0.0.1:0"], multicast_scouting=False,
                          insecure=True)
    angles = np.linspace(-np.pi, np.pi, 72, endpoint=False).astype(np.float32)
    got: list[int] = []
    try:
        with Bus.open(zenoh, Keys("swarmmap", run_id), "world", 0) as world, \
                Bus.open(zenoh, Keys("swarmmap", run_id), "learner", 0) as learner:
            assert not world.wait_alive("lidar", {"0"}, 60), log_path.read_text()[-2000:]
            pub = world.publisher(world.keys.scan(0))
            for seq in range(20):
                pub.put(Scan(run=run_id, sender=0, seq=seq, t=0.2 * seq, pose=[0.0, 0.0, 0.0], max_range=3.5,
                             angles=Tensor.of(angles, "<f4"), ranges=Tensor.of(np.full(72, 2.0, np.float32), "<f4"),
                             hit=Tensor.of(np.ones(72, np.uint8), "|u1"), last=seq == 19))
                if seq == 9:  # the learner's subscription comes late
                    assert wait_until(lambda: log_path.read_text().count("\n") >= 1, 30)
                    learner.subscribe(learner.keys.samples(0), Samples, lambda m: got.append(m.seq))
            assert wait_until(lambda: len(got) == 20, 30), (got, log_path.read_text()[-2000:])
    finally:
        proc.terminate()
        proc.wait(30)
    assert got == list(range(20))
    assert "robot 0 traversal done: 20 scans" in log_path.read_text()
