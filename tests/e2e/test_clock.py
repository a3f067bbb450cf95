"""A team on a clock (``learner.exchange_every_s``): learners in processes of their own over
Zenoh, half their messages lost, send a State every 2 s and never wait for one; one of
them killed mid-run is restarted, and the run finishes with maps learned and far fewer bytes
sent than a State a round."""

from __future__ import annotations

import json

import numpy as np
import pytest

from swarmmap.shared.learning.networks import load_model
from tests.harness import kill_at_round, leftovers, up

pytestmark = [pytest.mark.e2e, pytest.mark.faults]  # a fault trial (a learner killed): the faults tier

ROUNDS = 60


def test_learners_on_a_clock_over_lossy_links_survive_a_kill_and_learn(tmp_path):
    run_dir = tmp_path / "clock"
    proc = up(run_dir, "--preset", "smoke", "--robots", "3", "--no-observer", "--rounds", str(ROUNDS),
              "--set", "learner.exchange_every_s=2", "--set", "faults.link_success=0.5")
    try:
        kill_at_round(run_dir, "learner", 1, 20, after_s=0.5)
        assert proc.wait(600) == 0, (tmp_path / "clock.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["services"]["learner-1"]["restarts"] == 1
    assert "resuming from" in (run_dir / "logs" / "learner-1.log").read_text()
    values = sum(p.numel() for p in load_model(run_dir / "models" / "robot-0.pt").parameters())
    rows = [line.split(",") for line in (run_dir / "metrics.csv").read_text().splitlines()]
    head = rows[0]
    for robot, learner in summary["learners"].items():
        # Every robot learned: its final validation loss is well below its first.
        first = next(float(r[head.index("val_bce")]) for r in rows[1:] if r[head.index("robot")] == robot)
        assert learner["final_val_bce"] < 0.7 * first, (robot, learner["final_val_bce"], first)
        # A State every 2 s, not one a round (0.3-0.5 s here): well under half the bytes of a State a round
        # (float32; the restarted learner's counters go on from its checkpoint's).
        assert learner["bytes_sent"] < 0.5 * (ROUNDS + 1) * 4 * values, (robot, learner["bytes_sent"], values)
    assert not leftovers(run_dir), "a service outlived the run"
    assert np.isfinite([v["final_val_bce"] for v in summary["learners"].values()]).all()
