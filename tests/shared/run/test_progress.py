"""A run's progress line: the slowest learner's round, the team's losses, the time left; the
traversal's scans."""

from __future__ import annotations

import numpy as np

from swarmmap.shared.run.progress import TeamProgress, TraversalProgress, duration
from swarmmap.shared.wire.protocol import Metrics, Scan, Tensor


def metrics(robot: int, rnd: int, val: float, wall: float = 0.0, final: bool = False) -> Metrics:
    return Metrics(run="r", sender=robot, round=rnd, wall_time_s=wall, val_bce=val, consensus_error=0.0,
                   bytes_sent=0, bytes_received=0, final=final)


def scan(robot: int, last: bool = False) -> Scan:
    zeros = np.zeros(4, np.float32)
    return Scan(run="r", sender=robot, seq=0, t=0.0, pose=[0.0, 0.0, 0.0], max_range=3.5, angles=Tensor.of(zeros),
                ranges=Tensor.of(zeros), hit=Tensor.of(np.zeros(4, np.uint8), "|u1"), last=last)


def test_the_team_line_has_the_slowest_round_the_losses_and_the_time_left():
    team = TeamProgress(robots=3, rounds=100)
    assert team.line() is None
    team.add(metrics(0, 0, 0.7), now=0.0)
    assert "1 of 3 learners reporting" in team.line(now=0.0)
    team.add(metrics(1, 0, 0.6), now=0.0)
    team.add(metrics(2, 0, 0.8), now=0.0)
    for robot, val in ((0, 0.30), (1, 0.20), (2, 0.40)):
        team.add(metrics(robot, 20, val), now=10.0)
    team.add(metrics(2, 10, 0.9), now=11.0)  # late and older: ignored
    line = team.line(now=10.0)
    assert line.startswith("training: round 20 of 100 (20%), val_bce mean 0.3000 (min 0.2000, max 0.4000)"), line
    assert line.endswith("ETA 40 s"), line  # 20 rounds in 10 s, 80 rounds to go
    for robot in range(3):
        team.add(metrics(robot, 100, 0.1, final=True), now=50.0)
    assert team.line(now=50.0).endswith("3 of 3 finished") and team.finished() == 3


def test_a_learner_resumed_part_way_is_timed_by_what_this_process_saw():
    team = TeamProgress(robots=1, rounds=200)
    team.add(metrics(0, 100, 0.2, wall=1.0), now=0.0)  # resumed at round 100: its own clock has barely started
    assert team.eta_s(now=0.0) == 100 * 1.0 / 100
    team.add(metrics(0, 150, 0.1, wall=26.0), now=25.0)
    assert team.eta_s(now=25.0) == 50 * 25.0 / 50


def test_the_traversal_line_counts_scans_and_robots_at_the_end_of_their_paths():
    trip = TraversalProgress(robots=2, expected=10)
    assert trip.line() is None and not trip.started
    for _ in range(4):
        trip.add(scan(0), now=1.0)
    trip.add(scan(1, last=True), now=2.0)
    assert trip.line(now=3.0) == "traversal so far: 5 scans of about 10 (50%), 1 of 2 robots at the end of their paths, 2 s"
    trip.add(scan(0, last=True), now=4.0)
    assert trip.over and trip.line(now=99.0).startswith("traversal done: 6 scans of about 10 (60%), 2 of 2 robots")
    assert trip.line(now=99.0).endswith(", 3 s")


def test_durations_read_as_people_write_them():
    assert [duration(s) for s in (41, 200, 3900)] == ["41 s", "3 min 20 s", "1 h 05 min"]


def test_one_estimate_of_time_left_for_every_progress_line():
    from swarmmap.shared.run.progress import eta_words, time_left

    assert time_left(20, 100, 10.0) == 40.0  # 20 done in 10 s: 80 more take 40 s
    assert time_left(0, 100, 10.0) is None and time_left(5, 100, 0.0) is None
    assert time_left(0.5, 100, 10.0, at_least=1.0) is None  # too little done to tell
    assert time_left(120, 100, 10.0) == 0.0
    assert eta_words(200.0) == "ETA 3 min 20 s" and eta_words(None) == "time left not known yet"
