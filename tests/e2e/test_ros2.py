"""``swarmmap ros2`` against real rclpy peers in their own processes: two robots of a simulated
building (tests/e2e/ros2_robots.py) that drive to the goals they receive and publish scans and
odometry; the team maps them live and serves its maps to a subscriber that joins after it finished."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

from tests.conftest import REPO, SWARMMAP, clean_env, wait_until

pytestmark = pytest.mark.e2e
NAMESPACES = ("robot_a", "robot_b")


def need_rclpy() -> None:
    if os.environ.get("CI") == "true":
        import rclpy  # noqa: F401  (make setup installs the ros2 extra: missing, it is a failure)
    else:
        pytest.importorskip("rclpy", reason="rclpy not installed (pip install 'swarmmap[ros2]')")


def ros_env() -> dict[str, str]:
    """A ROS 2 domain of this test's own, on this host only."""
    return {**clean_env(), "ROS_DOMAIN_ID": str(random.randint(1, 100)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


class Lines:
    """A process's stderr read as it comes (the test waits on what it says)."""

    def __init__(self, proc: subprocess.Popen):
        self.lines: list[str] = []
        self.thread = threading.Thread(target=lambda: self.lines.extend(proc.stderr), daemon=True)
        self.thread.start()

    def has(self, text: str) -> bool:
        return any(text in line for line in self.lines)

    def text(self) -> str:
        return "".join(self.lines)


def test_exploring_ros2_robots_get_goals_and_live_maps_and_a_late_subscriber_the_final_ones(tmp_path):
    need_rclpy()
    env = ros_env()
    out, late, run_dir = tmp_path / "robots.json", tmp_path / "late.json", tmp_path / "run"
    # The robots' odometry starts at (0, 0, 0) each: their origins in the building are given.
    team = subprocess.Popen([*SWARMMAP, "ros2", "--namespaces", *NAMESPACES, "--extent", "0,0,10,6",
                             "--initial-poses", "1.5,1.5,0;1.5,4.5,1.5707963", "--explore", "uncertainty",
                             "--preset", "quickstart", "--rounds", "40", "--run-dir", str(run_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**env, "SWARMMAP_EXPLORE__LEG_S": "4"})
    said = Lines(team)
    robots = subprocess.Popen([sys.executable, "-m", "tests.e2e.ros2_robots", "drive", str(out), *NAMESPACES], cwd=REPO,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_until(lambda: said.has("serving its final maps") or team.poll() is not None, 300), said.text()[-3000:]
        assert team.poll() is None, said.text()[-3000:]
        finished = time.time()
        listener = subprocess.run([sys.executable, "-m", "tests.e2e.ros2_robots", "listen", str(late), *NAMESPACES],
                                  cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
        assert listener.returncode == 0, listener.stdout + listener.stderr
        team.send_signal(signal.SIGINT)  # the bridge serves until Ctrl-C
        team.wait(timeout=30)
        assert team.returncode == 0, said.text()[-3000:]
    finally:
        for proc in (team, robots):
            if proc.poll() is None:
                proc.terminate()
        robots_out, _ = robots.communicate(timeout=30)
    doc = json.loads(out.read_text())
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["robots"] == 2, summary
    # Goals, in frame map, for both robots: at least one for each leg (3 legs: 40 rounds, a goal every 10).
    for ns in NAMESPACES:
        goals = doc["goals"][ns]
        assert len(goals) >= 3 and {g[3] for g in goals} == {"map"}, (ns, goals, robots_out)
        assert all(0 <= g[1] <= 10 and 0 <= g[2] <= 6 for g in goals), goals
        assert doc["driven"][ns] > 1.0, doc["driven"]  # it drove toward them
    # The team's coverage of the building grew while they drove: the robots' own ground truth.
    coverage = [c for _, c in doc["coverage"]]
    first_goal = min(g[0] for ns in NAMESPACES for g in doc["goals"][ns])
    before = max(c for t, c in doc["coverage"] if t <= first_goal)
    assert coverage[-1] >= before + 0.1, (before, coverage[-1])
    ex = summary["exploration"]
    assert ex["policy"] == "uncertainty" and ex["coverage_of"] == "the map's extent" and ex["final_coverage"] > 0.3, ex
    # Maps came while the robots drove (they never fell silent), in ROS's conventions.
    saved = yaml.safe_load((run_dir / "maps" / "robot-0.yaml").read_text())
    for topic in ("/robot_a/map", "/robot_b/map", "/map"):
        live = [m for m in doc["maps"][topic] if m["t"] < finished]
        assert len(live) >= 2, topic  # refreshed as the team learned
        last = live[-1]
        assert last["frame"] == "map" and (last["width"], last["height"]) == (100, 60), last
        assert last["resolution"] == pytest.approx(saved["resolution"]) and last["origin"] == pytest.approx([0.0, 0.0])
        assert last["min"] == -1 and last["unknown"] > 0, last  # space nobody saw
        assert last["max"] <= 100 and last["free"] > 0, last
    assert any(m["walls"] > 0 for topic in ("/robot_a/map", "/robot_b/map") for m in doc["maps"][topic]), doc["maps"]
    assert "/robot_a/map_std" in doc["maps"]  # the BNN has a std
    # A subscriber that joined after the team finished got its final maps.
    got = json.loads(late.read_text())["maps"]
    for topic in ("/robot_a/map", "/robot_b/map", "/map"):
        assert got.get(topic), (topic, list(got))
        assert got[topic][-1]["min"] == -1 and got[topic][-1]["max"] <= 100
    # What the team heard is kept, replayable, and the stranger's publisher was named.
    for ns in NAMESPACES:
        assert list((run_dir / "input" / ns).glob("*.mcap")), ns
    world_log = (run_dir / "logs" / "world-0.log").read_text()
    assert "/robot_a/scan has 2 publishers (/swarmmap_test_robots, /swarmmap_test_stranger)" in world_log, world_log[-3000:]
    assert f"ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']}" in world_log
    assert "began their odometry at (0, 0, 0)" not in world_log  # their origins were given
    rows = np.genfromtxt(run_dir / "exploration.csv", delimiter=",", names=True)
    assert set(np.unique(rows["robot"]).astype(int)) == {0, 1} and rows["coverage"][-1] > rows["coverage"][0]


@pytest.mark.faults
def test_a_ros2_team_learns_while_it_hears_and_ctrl_c_keeps_what_it_heard(tmp_path):
    """Not exploring: the robots stand and stream (a driver never falls silent); the team learns
    online, its maps come meanwhile, and Ctrl-C mid-run keeps every scan heard."""
    need_rclpy()
    env = ros_env()
    out, run_dir = tmp_path / "robots.json", tmp_path / "run"
    team = subprocess.Popen([*SWARMMAP, "ros2", "--namespaces", *NAMESPACES, "--preset", "smoke", "--rounds", "5000",
                             "--run-dir", str(run_dir)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    said = Lines(team)
    robots = subprocess.Popen([sys.executable, "-m", "tests.e2e.ros2_robots", "drive", str(out), *NAMESPACES], cwd=REPO,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        def maps_came() -> bool:
            try:
                maps = json.loads(out.read_text())["maps"]
            except (OSError, ValueError):
                return False
            return all(len(maps.get(f"/{ns}/map", [])) >= 2 for ns in NAMESPACES)

        assert wait_until(lambda: maps_came() or team.poll() is not None, 240), said.text()[-3000:]
        assert team.poll() is None, said.text()[-3000:]
        team.send_signal(signal.SIGINT)
        team.wait(timeout=60)
    finally:
        for proc in (team, robots):
            if proc.poll() is None:
                proc.terminate()
        robots.communicate(timeout=30)
    assert team.returncode == 130, said.text()[-3000:]
    doc = json.loads(out.read_text())
    last = doc["maps"]["/robot_a/map"][-1]
    assert last["min"] == -1 and last["frame"] == "map"  # the space behind the walls nobody saw
    world_log = (run_dir / "logs" / "world-0.log").read_text()
    # Their odometry each began at its own origin and no initial poses were given: said, not silently mapped.
    assert "robots robot_a, robot_b each began their odometry at (0, 0, 0)" in world_log, world_log[-3000:]
    from swarmmap.shared.world.datasets import read_log

    for ns in NAMESPACES:  # every scan heard until Ctrl-C, kept
        (bag,) = (run_dir / "input" / ns).glob("*.mcap")
        assert len(read_log(bag)) >= 0.9 * doc["heard"][ns] - 5, (ns, doc["heard"])
