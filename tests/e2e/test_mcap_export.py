"""A run written as a rosbag2 in MCAP (``swarmmap up --mcap``), read back with rosbags."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e


def test_a_runs_bag_holds_every_topic_it_lists_and_the_final_maps(tmp_path):
    from rosbags.highlevel import AnyReader

    run_dir = tmp_path / "run"
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--robots", "3", "--rounds", "20", "--mcap",
                           "--set", "observer.map_resolution_m=0.05", "--run-dir", str(run_dir)],
                          capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
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
