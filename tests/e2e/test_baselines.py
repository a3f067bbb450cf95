"""Every baseline and graph runs through the whole system."""

from __future__ import annotations

import csv
import json
import re
import subprocess

import pytest

from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e


def up(run_dir, *extra):
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--rounds", "30",
                           "--run-dir", str(run_dir), *extra], capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((run_dir / "summary.json").read_text())["learners"]


def test_centralized_baseline_is_one_model_for_everyone(tmp_path):
    learners = up(tmp_path / "c", "--transport", "inproc", "--set", "learner.algorithm=centralized")
    finals = {v["final_val_bce"] for v in learners.values()}
    assert len(finals) == 1 and finals.pop() < learners["0"]["first_val_bce"]


def test_dsgt_over_zenoh_on_a_graph_file_exchanging_every_other_round(tmp_path):
    """Between exchanges a baseline takes local steps (no mixing): every learner finishes and learns."""
    graph = tmp_path / "graph.yaml"
    graph.write_text("edges: [[0, 1], [1, 2]]\n")
    learners = up(tmp_path / "g", "--set", "learner.algorithm=dsgt", "--set", "learner.graph=file", "--set", "learner.exchange_every=2",
                  "--set", f"learner.graph_file={graph}", "--set", "learner.lr_start=0.3", "--set", "learner.lr_finish=0.3")
    assert all(v["finished"] and v["final_val_bce"] < v["first_val_bce"] for v in learners.values())
    # Robot 0's only neighbour is 1: it receives one State per exchange, robot 1 two.
    assert learners["1"]["bytes_received"] > 1.8 * learners["0"]["bytes_received"]


def test_dsgd_exchanges_every_few_rounds(tmp_path):
    learners = up(tmp_path / "dsgd", "--rounds", "20", "--transport", "inproc", "--set", "learner.algorithm=dsgd",
                  "--set", "learner.exchange_every=2", "--set", "learner.lr_start=0.3", "--set", "learner.lr_finish=0.3")
    assert all(v["finished"] and v["final_val_bce"] < v["first_val_bce"] for v in learners.values())


def test_individual_and_disk_graph(tmp_path):
    alone = up(tmp_path / "i", "--rounds", "15", "--set", "learner.algorithm=individual")
    rows = list(csv.DictReader((tmp_path / "i" / "metrics.csv").open()))
    assert all(float(r["consensus_error"]) == 0.0 and int(r["bytes_received"]) == 0 for r in rows)
    assert all(v["final_val_bce"] < v["first_val_bce"] for v in alone.values())
    disk = up(tmp_path / "d", "--rounds", "15", "--set", "learner.graph=disk", "--set", "learner.comm_radius_m=0.01",
              "--transport", "inproc")
    assert all(v["finished"] for v in disk.values())  # nobody within 1 cm: each trains alone


def test_online_training_starts_while_the_robots_drive(tmp_path):
    learners = up(tmp_path / "o", "--set", "learner.data=online", "--set", "learner.window_scans=30",
                  "--set", "world.time_scale=4")
    assert all(v["finished"] and v["final_val_bce"] < v["first_val_bce"] for v in learners.values())
    world = (tmp_path / "o" / "logs" / "world-0.log").read_text().splitlines()
    learner = (tmp_path / "o" / "logs" / "learner-0.log").read_text().splitlines()
    traversal_end = next(line for line in world if "traversal done" in line)[:23]
    first_round = next(line for line in learner if "round 0:" in line)[:23]
    assert first_round < traversal_end, "online training should begin before the traversal ends"


@pytest.mark.faults
def test_a_dynamic_disk_graph_links_robots_only_while_in_range(tmp_path):
    """DiNNO's setting over Zenoh: training while the robots drive, each hearing only the robots
    within comm_radius_m at the time (States carry positions). In the smoke plan at 3.5 m the
    robots are sometimes in range and sometimes not: every learner finishes, some rounds use a
    neighbour's State, and messages from out of range are ignored rather than waited for."""
    learners = up(tmp_path / "o", "--rounds", "20", "--set", "learner.data=online", "--set", "learner.window_scans=30",
                  "--set", "world.time_scale=4", "--set", "learner.graph=disk", "--set", "learner.comm_radius_m=3.5",
                  "--set", "learner.round_wait_s=0.3")
    assert all(v["finished"] for v in learners.values())
    rows = list(csv.DictReader((tmp_path / "o" / "metrics.csv").open()))
    assert any(float(r["consensus_error"]) > 0 for r in rows), "no round ever heard a neighbour in range"
    logs = "".join((tmp_path / "o" / "logs" / f"learner-{i}.log").read_text() for i in range(3))
    ignored = [int(x) for x in re.findall(r"(\d+) message\(s\) from neighbours out of range ignored", logs)]
    assert ignored and max(ignored) > 0, logs[-2000:]
