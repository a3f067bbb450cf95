"""The recorder's rules for when a run is over and how it ended, and its metrics file."""

from __future__ import annotations

import csv

from swarmmap.services.recorder import MetricsRecorder, RunTracker, draw_overview
from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.protocol import Metrics


def metrics(robot: int, rnd: int, final: bool = False) -> Metrics:
    return Metrics(run="r", sender=robot, round=rnd, wall_time_s=1.0, val_bce=0.5, consensus_error=0.1,
                   bytes_sent=1, bytes_received=1, final=final)


def test_the_run_succeeds_once_every_learner_sent_its_final_metrics():
    t = RunTracker(3)
    for i in range(3):
        t.on_alive("learner", str(i), True)
        t.on_metrics(metrics(i, 0))
    t.on_metrics(metrics(0, 10, final=True))
    t.on_metrics(metrics(1, 10, final=True))
    assert t.outcome() is None
    t.on_metrics(metrics(2, 10, final=True))
    assert t.outcome() == (True, "all 3 learners finished")
    t.on_alive("learner", "1", False)  # leaving after the end is no failure
    assert t.outcome()[0]


def test_a_learner_that_leaves_and_is_not_back_in_time_fails_the_run():
    t = RunTracker(2, rejoin_timeout=20)
    for i in range(2):
        t.on_alive("learner", str(i), True, now=0)
    t.on_alive("learner", "1", False, now=10)  # killed; the launcher restarts it
    assert t.outcome(now=25) is None
    t.on_alive("learner", "1", True, now=26)  # back: the run goes on
    assert t.outcome(now=100) is None
    t.on_alive("learner", "0", False, now=100)
    assert t.outcome(now=119) is None
    ok, reason = t.outcome(now=120.5)
    assert not ok and reason.startswith("learner 0 left before finishing") and "not back within 20 s" in reason


def test_a_learner_whose_host_is_unreachable_has_the_longer_wait_and_the_rejoin_window_from_its_return():
    t = RunTracker(2, rejoin_timeout=20, unreachable_timeout=600)
    for i in range(2):
        t.on_alive("learner", str(i), True, now=0)
        t.on_alive("router", f"r{i}", True, now=0)
    t.on_alive("learner", "1", False, now=10)
    t.on_alive("router", "r1", False, now=11)  # a cut: its host's router is gone too
    assert t.outcome(now=300) is None  # 290 s away, unreachable: waited for
    t.on_alive("router", "r1", True, now=400)  # the link is back; the learner's token comes a moment later
    assert t.outcome(now=401) is None  # 20 s from its host's return, not from its leaving
    t.on_alive("learner", "1", True, now=402)
    assert t.outcome(now=500) is None
    assert [(a["robot"], a["back_after_s"]) for a in t.absences] == [(1, 392.0)]
    t.on_alive("learner", "0", False, now=510)  # a learner that leaves while its host is there: 20 s
    ok, why = t.outcome(now=531)
    assert not ok and why.startswith("learner 0 left before finishing") and "unreachable" not in why


def test_an_unreachable_host_that_stays_away_fails_the_run_naming_it():
    t = RunTracker(2, rejoin_timeout=20, unreachable_timeout=60)
    t.on_alive("learner", "1", True, now=0)
    t.on_alive("learner", "1", False, now=5)
    t.on_alive("router", "r1", False, now=6)
    assert t.outcome(now=60) is None
    ok, why = t.outcome(now=66)
    assert not ok and "its host r1 unreachable" in why and "not back within 60 s" in why


def test_a_learner_that_leaves_before_finishing_fails_the_run_and_is_named():
    t = RunTracker(3)
    for i in range(3):
        t.on_alive("learner", str(i), True)
    t.on_metrics(metrics(0, 10, final=True))
    t.on_alive("learner", "0", False)  # finished, then left: fine
    assert t.outcome() is None
    t.on_alive("learner", "2", False)
    ok, reason = t.outcome()
    assert not ok and "learner 2" in reason
    t.on_alive("learner", "1", False)  # the first failure is the one reported
    assert "learner 2" in t.outcome()[1]


def test_streamers_and_the_world_are_needed_only_until_the_learners_have_their_data():
    t = RunTracker(2)
    for svc, i in (("lidar", 0), ("lidar", 1), ("world", 0), ("learner", 0), ("learner", 1)):
        t.on_alive(svc, str(i), True)
    t.on_metrics(metrics(0, 0))
    t.on_alive("lidar", "0", False)  # learner 0 already trains
    assert t.outcome() is None
    t.on_alive("lidar", "1", False)
    ok, reason = t.outcome()
    assert not ok and "lidar 1" in reason

    t = RunTracker(1)
    t.on_alive("world", "0", True)
    t.on_alive("world", "0", False)
    assert "world" in t.outcome()[1]


def test_tokens_never_seen_and_foreign_ids_are_ignored():
    t = RunTracker(2)
    t.on_alive("learner", "1", False)  # a delete without a put (e.g. history) says nothing
    t.on_alive("learner", "x", True)
    assert t.outcome() is None and t.learners_missing() == [0, 1]


def test_a_resumed_metrics_file_goes_on_after_its_rows_and_writes_none_twice(tmp_path):
    """A learner that resumes from its checkpoint reports rounds the file holds already: they are
    not written again, the first rows stay the first, and a half-written last row is cut off."""
    path = tmp_path / "metrics.csv"
    rec = MetricsRecorder(path)
    for k in (0, 5, 10):
        rec.add(metrics(0, k))
    rec.close()
    with path.open("a") as f:
        f.write("0,15,3.0,0.4")  # a recorder killed while writing this row
    rec = MetricsRecorder(path)
    assert rec.first[0].round == 0 and rec.latest[0].round == 10
    written = [rec.add(metrics(0, k)) for k in (5, 10, 15, 20)] + [rec.add(metrics(0, 20, final=True))]
    rec.close()
    assert written == [False, False, True, True, True]
    rows = list(csv.DictReader(path.open()))
    assert [(r["round"], r["final"]) for r in rows] == [("0", "0"), ("5", "0"), ("10", "0"), ("15", "0"), ("20", "0"), ("20", "1")]
    assert rec.first[0].round == 0 and rec.final[0].round == 20


def test_the_summary_of_a_resumed_run_keeps_its_start_and_adds_up_the_wall_time(tmp_path):
    from swarmmap.services.recorder import summary
    from swarmmap.shared.run.config import resolve

    cfg = resolve({"robots": 1}, environ={})
    rec = MetricsRecorder(tmp_path / "metrics.csv")
    rec.add(Metrics(run="r", sender=0, round=0, wall_time_s=1.0, val_bce=0.7, consensus_error=0, bytes_sent=1, bytes_received=1))
    rec.close()
    first = summary(cfg, rec, False, "interrupted", 17.5, started=1000.0)
    rec = MetricsRecorder(tmp_path / "metrics.csv")
    rec.add(Metrics(run="r", sender=0, round=0, wall_time_s=0.5, val_bce=0.2, consensus_error=0, bytes_sent=1, bytes_received=1))
    again = summary(cfg, rec, True, "all 1 learners finished", 11.5, started=2000.0, earlier=first)
    assert again["learners"]["0"]["first_val_bce"] == 0.7, "the first attempt's first val_bce was lost"
    assert again["started"] == 1000.0 and again["wall_time_s"] == 29.0 and again["earlier_wall_time_s"] == 17.5
    assert again["attempts"] == 2


def test_a_stall_names_the_learners_that_reported_nothing_then_the_lowest():
    from swarmmap.services.recorder import StallWatch

    w = StallWatch(3, timeout=10, now=0)
    assert w.stalled(now=9) is None
    for t in (5, 12):
        w.on_scan(now=t)
    why = w.stalled(now=22.5)
    assert "no progress" in why and "10 s" in why and "[0, 1, 2] reported no round after the 2 scans" in why
    w.on_metrics(metrics(0, 40), now=23)
    w.on_metrics(metrics(2, 60), now=24)
    assert w.stalled(now=33) is None
    assert w.held_up_by() == [1] and "learner(s) [1] reported no round" in w.stalled(now=34.5)
    w.on_metrics(metrics(1, 60), now=35)
    assert w.held_up_by() == [0] and "learner(s) [0] are at round 40, the lowest (the team's newest is 60)" in w.stalled(now=45)
    w.on_metrics(metrics(0, 60, final=True), now=46)
    assert w.held_up_by() == [1, 2]  # the one that finished holds nothing up
    for t in (50, 54, 58):  # a finished learner says its final Metrics again, an old round comes late: no progress
        w.on_metrics(metrics(0, 60, final=True), now=t)
        w.on_metrics(metrics(1, 20), now=t)
    assert "learner(s) [1, 2] are at round 60" in w.stalled(now=56.5)


def test_the_recorder_refuses_a_finished_run_and_a_run_directory_it_cannot_write(tmp_path, capsys):
    import pytest

    from swarmmap.services.recorder import refuse_run_dir
    from tests.conftest import recorded_run

    finished = recorded_run(tmp_path / "done")
    with pytest.raises(SystemExit) as info:
        refuse_run_dir(finished)
    assert info.value.code == 2 and "holds a finished run" in capsys.readouterr().err
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(SystemExit):
        refuse_run_dir(blocker / "run")
    assert "is a file" in capsys.readouterr().err
    refuse_run_dir(tmp_path / "new")  # a new one is fine


def test_an_overview_that_cannot_be_drawn_is_logged_and_never_fails_the_run(tmp_path, caplog):
    (tmp_path / "maps").mkdir()
    (tmp_path / "groundtruth.npz").write_bytes(b"not an npz")
    (tmp_path / "maps" / "robot-0.npz").write_bytes(b"nor this")
    draw_overview(RunConfig(run_dir=tmp_path), {})
    assert "could not draw" in caplog.text and str(tmp_path / "overview.png") in caplog.text
    assert not (tmp_path / "overview.png").exists()


def test_the_log_says_each_phase_once_and_a_progress_line_every_so_often(caplog):
    import logging

    from swarmmap.services.recorder import PhaseLog

    tracker, phases = RunTracker(2), PhaseLog(robots=2, rounds=10, every=10.0)
    with caplog.at_level(logging.INFO, logger="recorder"):
        phases.tick(tracker, now=0.0)
        for i in range(2):
            tracker.on_alive("learner", str(i), True)
        phases.tick(tracker, now=1.0)
        for i in range(2):
            m = metrics(i, 5)
            tracker.on_metrics(m)
            phases.team.add(m, now=2.0)
        phases.tick(tracker, now=2.0)
        phases.tick(tracker, now=5.0)  # too soon for another line
        phases.tick(tracker, now=12.5)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "every learner is alive (2); waiting for the world to drive"
    assert lines[1] == "training: the learners have their points"
    assert lines[2].startswith("training: round 5 of 10 (50%), val_bce mean 0.5000") and lines[3].startswith("training: round 5")
    assert len(lines) == 4


def test_the_summary_says_when_the_run_started_and_finished(tmp_path):
    import time

    from swarmmap.services.recorder import summary
    from swarmmap.shared.run.config import resolve

    rec = MetricsRecorder(tmp_path / "metrics.csv")
    doc = summary(resolve({"robots": 1}, environ={}), rec, True, "all 1 learners finished", 30.0, started=1000.0)
    assert doc["started"] == 1000.0 and abs(doc["finished"] - time.time()) < 5


def test_a_member_that_reports_a_new_round_now_and_then_hides_no_stall():
    """Progress is the team's: one learner reporting a new round every 500 s while the others
    are stuck (or after they have finished) does not keep a 600 s stall timeout from firing."""
    from swarmmap.services.recorder import StallWatch

    w = StallWatch(3, timeout=600, now=0)
    for r in range(3):
        w.on_metrics(metrics(r, 5), now=1)
    for k, t in enumerate(range(500, 5000, 500)):
        w.on_metrics(metrics(1, 6 + k), now=t)
        if t >= 601:
            assert w.stalled(now=t) is not None, f"no stall at {t} s"
    assert w.held_up_by() == [0, 2]
    two = StallWatch(2, timeout=600, now=0)
    two.on_metrics(metrics(0, 100, final=True), now=10)
    for k, t in enumerate(range(500, 3000, 500)):
        two.on_metrics(metrics(1, 1 + k), now=t)
    assert "learner(s) [1]" in two.stalled(now=611)


def test_the_recorder_refuses_metrics_no_learner_of_the_run_sends(tmp_path):
    """Beyond the run's rounds, a final one before the last round, a robot the run does not have,
    or an earlier round from the same process: refused; a restarted learner (another pid) may
    report its rounds again. A flood of new rounds writes at most the run's rows."""
    import pytest

    from swarmmap.services.recorder import Recorder
    from swarmmap.shared.wire.protocol import ProtocolError

    cfg = RunConfig(run_dir=tmp_path, robots=2, learner={"rounds": 10})
    rec = Recorder(cfg)

    def send(robot, rnd, final=False, pid=7):
        m = metrics(robot, rnd, final).model_copy(update={"pid": pid})
        rec.check_metrics(m)
        rec.on_metrics(m)

    send(0, 4)
    for bad, reason in (((0, 11), "beyond-rounds"), ((0, 5, True), "beyond-rounds"), ((2, 1), "unknown-sender"),
                        ((0, 3), "out-of-order")):
        with pytest.raises(ProtocolError) as err:
            send(*bad)
        assert err.value.reason == reason
    send(0, 3, pid=8)  # restarted: its checkpoint's rounds again
    refused = 0
    for rnd in range(100_000):
        try:
            send(1, rnd % 50_000, pid=9 + rnd // 50_000)
        except ProtocolError:
            refused += 1
    rec.metrics.close()
    rows = (tmp_path / "metrics.csv").read_text().splitlines()
    assert refused == 100_000 - 22 and len(rows) == 1 + 2 + 11


def test_the_summary_counts_each_robots_refused_messages_by_who_refused_them(tmp_path):
    """A learner's final Metrics say whose messages it refused; summary.json keeps that per learner
    and adds it up per robot (``refusals``: what the robot's neighbours refused of it)."""
    from swarmmap.services.recorder import summary

    cfg = RunConfig(run_dir=tmp_path, robots=3, learner={"rounds": 10})
    rec = MetricsRecorder(tmp_path / "metrics.csv")
    for robot, refused in ((0, [[2, 40]]), (1, [[0, 1], [2, 60]]), (2, [])):
        rec.add(metrics(robot, 10, final=True).model_copy(update={"refused_from": refused}))
    doc = summary(cfg, rec, True, "all 3 learners finished", 12.0)
    assert doc["learners"]["1"]["refused_from"] == {"0": 1, "2": 60} and doc["refusals"] == {"0": 1, "2": 100}
