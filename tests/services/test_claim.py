"""Robot ids claimed by look-alike containers (services/claim.py) and compose's start of a run:
replicas that claim at once get distinct ids, a holder gets its own id back, one too many is
refused with a message naming the setting; a finished run is refused, an unfinished one is
resumed only when asked (SWARMMAP_UP__RESUME) and with its own settings, and a refused start
changes not a byte of the run directory."""

from __future__ import annotations

import json
import multiprocessing
import socket

import pytest

from swarmmap.services.claim import ClaimError, claim_robot, forget_claims, start
from swarmmap.shared.config import task_robot


def _claim_at_once(folder, barrier, holder, robots, out):
    barrier.wait()
    out.put((holder, claim_robot(folder, "learner", robots, holder=holder)))


def test_replicas_claiming_at_once_get_distinct_ids(tmp_path):
    robots = 8
    ctx = multiprocessing.get_context("fork")
    barrier, out = ctx.Barrier(robots), ctx.Queue()
    procs = [ctx.Process(target=_claim_at_once, args=(tmp_path, barrier, f"c{i}", robots, out)) for i in range(robots)]
    for p in procs:
        p.start()
    got = dict(out.get(timeout=60) for _ in procs)
    for p in procs:
        p.join(timeout=60)
    assert sorted(got.values()) == list(range(robots))
    assert json.loads((tmp_path / "learner.json").read_text()) == got


def test_a_holder_gets_its_own_id_back_and_services_claim_apart(tmp_path):
    assert [claim_robot(tmp_path, "learner", 3, holder=h) for h in ("a", "b")] == [0, 1]
    assert claim_robot(tmp_path, "learner", 3, holder="a") == 0  # a restarted container
    assert claim_robot(tmp_path, "lidar", 3, holder="b") == 0  # lidar ids are claimed apart from learner ids
    assert claim_robot(tmp_path, "learner", 3, holder="c") == 2


def test_one_holder_too_many_is_refused_and_a_new_up_claims_afresh(tmp_path):
    for h in "abc":
        claim_robot(tmp_path, "lidar", 3, holder=h)
    with pytest.raises(ClaimError, match=r"all 3 robot ids of lidar are held.*SWARMMAP_ROBOTS=3"):
        claim_robot(tmp_path, "lidar", 3, holder="d")
    forget_claims(tmp_path)
    assert claim_robot(tmp_path, "lidar", 3, holder="d") == 0


def test_task_robot_claims_by_host_name_unless_given(tmp_path, capsys):
    env = {"SWARMMAP_ROBOT_CLAIMS": str(tmp_path)}
    claim_robot(tmp_path, "learner", 2, holder="someone-else")
    assert task_robot(None, 2, "learner.robot", env) == 1
    assert json.loads((tmp_path / "learner.json").read_text())[socket.gethostname()] == 1
    assert task_robot(0, 2, "learner.robot", env) == 0  # --robot wins over a claim
    assert task_robot(None, 2, "learner.robot", env | {"SLURM_PROCID": "0"}) == 0  # and so does the SLURM rank
    for holder in ("x", "y"):
        claim_robot(tmp_path, "lidar", 2, holder=holder)
    with pytest.raises(SystemExit) as info:
        task_robot(None, 2, "lidar.robot", env)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "lidar.robot: no robot id to claim" in err and "SWARMMAP_ROBOTS=2" in err


def compose_env(run_dir, robots: int) -> dict[str, str]:
    return {"SWARMMAP_PRESET": "smoke", "SWARMMAP_RUN_ID": "compose", "SWARMMAP_RUN_DIR": str(run_dir),
            "SWARMMAP_ROBOTS": str(robots), "SWARMMAP_ROBOT_CLAIMS": str(run_dir.parent / "shared")}


def test_start_writes_config_and_credentials_forgets_claims_and_says_ok(tmp_path):
    run_dir, shared = tmp_path / "compose", tmp_path / "shared"
    claim_robot(shared, "learner", 3, holder="a container of an earlier up")
    assert start(compose_env(run_dir, 3)) == 0
    assert "robots: 3" in (run_dir / "config.yaml").read_text()
    assert {"ca.pem", "acl.json5", "learner-2.key", "lidar-2.pem", "router-0.key"} <= {p.name for p in (run_dir / "secrets").iterdir()}
    assert not list(shared.glob("*.json")) and (shared / "start").read_text() == "ok\n"
    assert start(compose_env(run_dir, 3) | {"SWARMMAP_UP__RESUME": "true"}) == 0  # the same run again, resumed


def test_start_resumes_an_unfinished_run_only_when_asked(tmp_path, capsys):
    run_dir, shared = tmp_path / "compose", tmp_path / "shared"
    assert start(compose_env(run_dir, 3)) == 0
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert start(compose_env(run_dir, 3)) == 2
    err = capsys.readouterr().err
    assert f"{run_dir} holds a run that did not finish" in err and "SWARMMAP_UP__RESUME=true" in err and "SWARMMAP_RUN_ID" in err
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before
    assert "SWARMMAP_UP__RESUME=true" in (shared / "start").read_text()


def test_start_refuses_a_run_directory_holding_another_run_and_changes_nothing(tmp_path, capsys):
    run_dir, shared = tmp_path / "compose", tmp_path / "shared"
    assert start(compose_env(run_dir, 3)) == 0
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert start(compose_env(run_dir, 5) | {"SWARMMAP_UP__RESUME": "true"}) == 2
    err = capsys.readouterr().err
    assert "robots 3 there, 5 here" in err and "SWARMMAP_RUN_ID" in err
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before
    assert "robots 3 there, 5 here" in (shared / "start").read_text()  # what the run's other containers say


def test_start_refuses_a_finished_run_resumed_or_not_and_changes_nothing(tmp_path, capsys):
    run_dir = tmp_path / "compose"
    assert start(compose_env(run_dir, 3)) == 0
    (run_dir / "summary.json").write_text('{"ok": true}\n')  # what the recorder writes when every learner finished
    before = {p.relative_to(run_dir): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    for env in ({}, {"SWARMMAP_UP__RESUME": "true"}):
        assert start(compose_env(run_dir, 3) | env) == 2
        err = capsys.readouterr().err
        assert f"{run_dir} holds a finished run, which is never overwritten" in err and "SWARMMAP_RUN_ID" in err
    assert {p.relative_to(run_dir): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["compose", "shared"]  # nothing moved aside either


def test_start_refuses_a_wrong_setting_and_says_why(tmp_path, capsys):
    assert start(compose_env(tmp_path / "compose", 3) | {"SWARMMAP_ROBOTS": "100"}) == 2
    assert "robots" in capsys.readouterr().err and "robots" in (tmp_path / "shared" / "start").read_text()
    assert not (tmp_path / "compose").exists()
