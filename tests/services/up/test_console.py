"""``up``'s console: the progress line in place on a terminal, periodic lines in a log, and the
closing block of a run directory as the recorder and ``up`` leave it."""

from __future__ import annotations

import io
import logging

from swarmmap.services.up.console import CLEAR, Console, closing_block
from tests.conftest import recorded_run


def test_on_a_terminal_the_line_updates_in_place_and_a_log_line_clears_it_first():
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    logging.getLogger().addHandler(handler)
    try:
        console = Console(stream=out, tty=True)
        console.progress("training: round 1 of 9", now=0.0)
        console.progress("training: round 2 of 9", now=0.1)  # too soon: not drawn
        console.progress("training: round 3 of 9", now=1.0)
        logging.getLogger("up").warning("a log line")
        console.close()
    finally:
        logging.getLogger().removeHandler(handler)
    assert out.getvalue() == (CLEAR + "training: round 1 of 9" + CLEAR + "training: round 3 of 9" + CLEAR + "a log line\n")


def test_elsewhere_a_plain_line_is_logged_every_so_often(caplog):
    out = io.StringIO()
    console = Console(stream=out, tty=False, every_s=10.0)
    with caplog.at_level(logging.INFO, logger="up"):
        console.progress("round 1", now=0.0)
        console.progress("round 2", now=5.0)
        console.progress("round 3", now=5.0, force=True)  # a new phase: at once
        console.progress("round 4", now=16.0)
    assert [r.getMessage() for r in caplog.records] == ["round 1", "round 3", "round 4"]
    assert out.getvalue() == ""


def test_the_closing_block_says_how_it_ended_where_everything_went_and_what_to_run_next(tmp_path):
    run_dir = tmp_path / "run"
    recorded_run(run_dir, ok=True)
    text = closing_block(run_dir)
    assert "run demo-1: ok (all 2 learners finished) in 42 s" in text
    assert "robot 0 0.1250  robot 1 0.2350" in text and "team mean      0.1800 over 2 robot(s)" in text
    assert "5.0 MB by the learners" in text and f"run directory  {run_dir}" in text
    assert f"rerun {run_dir / 'recording.rrd'}" in text and f"swarmmap experiment score {run_dir} --ensemble" in text  # fourier
    assert f"swarmmap compare {run_dir}" in text and "swarmmap logs" not in text


def test_a_failed_run_points_at_its_logs(tmp_path):
    run_dir = tmp_path / "run"
    recorded_run(run_dir, ok=False)
    text = closing_block(run_dir)
    assert "FAILED (learner 1 left before finishing)" in text and f"swarmmap logs {run_dir}" in text


def test_a_bayesian_run_is_scored_by_its_own_std_maps(tmp_path):
    run_dir = recorded_run(tmp_path / "run", model="bnn")
    text = closing_block(run_dir)
    assert f"swarmmap experiment score {run_dir}  " in text and "--ensemble" not in text


def test_an_interrupted_run_says_so_and_names_the_resume_command(tmp_path):
    import json

    run_dir = recorded_run(tmp_path / "run", ok=False)
    summary = json.loads((run_dir / "summary.json").read_text())
    summary.update(status=130, reason="interrupted (Ctrl-C or SIGTERM) after 12 s")
    (run_dir / "summary.json").write_text(json.dumps(summary))
    text = closing_block(run_dir)
    assert "INTERRUPTED (interrupted (Ctrl-C or SIGTERM) after 12 s)" in text and "FAILED" not in text
    assert f"swarmmap up --run-dir {run_dir} --resume" in text
