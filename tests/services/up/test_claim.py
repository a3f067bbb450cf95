"""Robot ids claimed by look-alike containers (services/up/claim.py) and compose's start of a run:
replicas that claim at once get distinct ids, a holder gets its own id back, one too many is
refused with a message naming the setting; a finished run is refused, an unfinished one is
resumed only when asked (SWARMMAP_UP__RESUME) and with its own settings, and a refused start
changes not a byte of the run directory; the run's signer issues each identity to one key,
writes no private key and its certificates carry a secure run."""

from __future__ import annotations

import fcntl
import json
import multiprocessing
import socket
import threading

import pytest

from swarmmap.services.up.claim import compose_identities, nobody_running, start
from swarmmap.shared.run.config import ZenohSettings, task_robot
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.claims import ClaimError, claim_robot, forget_claims
from swarmmap.shared.wire.protocol import Keys
from swarmmap.shared.wire.secrets import SecretsError, access_policy, enrol
from tests.conftest import REPO, free_port, wait_until


def _claim_at_once(folder, barrier, holder, robots, out):
    barrier.wait()
    out.put((holder, claim_robot(folder, "learner", robots, holder=holder)))


@pytest.mark.integration
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
    assert {"learner-2@compose", "lidar-2@compose", "router-0@compose"} <= {p.name for p in (run_dir / "secrets").iterdir()}
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


@pytest.mark.timeout(120)
@pytest.mark.integration
def test_the_signer_issues_each_identity_to_one_key_and_no_private_key_is_shared(tmp_path):
    run_dir, shared, verdicts = tmp_path / "compose", tmp_path / "shared", tmp_path / "start"
    signer, requests = verdicts / "signer", shared / "requests"  # compose: signer's folder read-only to the services
    env = compose_env(run_dir, 2) | {"SWARMMAP_ZENOH__SIGNER": str(signer), "SWARMMAP_ZENOH__SECRETS": str(tmp_path / "own-start"),
                                     "SWARMMAP_START": str(verdicts), "SWARMMAP_ZENOH__SIGNER_REQUESTS": str(requests)}
    stop = threading.Event()
    thread = threading.Thread(target=start, args=(env, True, stop, REPO / "compose.yaml"), daemon=True)
    thread.start()
    try:
        assert wait_until(lambda: (verdicts / "start").exists() and (verdicts / "start").read_text() == "ok\n", 60, 0.1)
        assert not (shared / "start").exists() and (verdicts / "running").is_file()
        containers = {name: tmp_path / "containers" / name for name in ("router", "learner-a", "learner-b")}
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        keys = Keys("swarmmap", "compose")
        router = ZenohSettings(mode="router", listen=[endpoint], multicast_scouting=False, secrets=containers["router"],
                               signer=signer, signer_requests=requests, connect_timeout_s=30)
        member = ZenohSettings(connect=[endpoint], multicast_scouting=False, secrets=containers["learner-a"], signer=signer,
                               signer_requests=requests, connect_timeout_s=30)
        with Bus.open(router, keys, "router", 0, policy=access_policy(keys, 2)), Bus.open(member, keys, "learner", 1) as learner:
            learner.announce()
            assert wait_until(lambda: ("learner", "1") in learner.alive("learner"), 10)  # a secure session, end to end
        with pytest.raises(SecretsError, match="already issued to another key"):  # a second container claiming learner 1
            enrol(containers["learner-b"] / "learner-1@compose", "learner-1", "compose", signer, 30, requests=requests)
        for tool in ("up-0", "status-0", "learner-2"):  # identities no service of this compose run holds
            with pytest.raises(SecretsError, match=f"{tool}@compose is no identity of a service of run compose"):
                enrol(containers["learner-b"] / f"{tool}@compose", tool, "compose", signer, 30, requests=requests)
        again = enrol(containers["learner-a"] / "learner-1@compose", "learner-1", "compose", signer, 30,
                      requests=requests)  # its restart
        assert (again / "cert.pem").is_file()
    finally:
        stop.set()
        thread.join(30)
    keys_on_disk = [p for p in tmp_path.rglob("*") if p.is_file() and b"PRIVATE KEY" in p.read_bytes()]
    assert sorted({p.relative_to(tmp_path / "containers").parts[0] for p in keys_on_disk}) == ["learner-a", "learner-b", "router"], \
        f"private keys outside the containers' own folders: {keys_on_disk}"
    assert not (run_dir / "secrets").exists()


def test_the_signer_signs_the_services_compose_runs_only(tmp_path):
    assert set(compose_identities(2, REPO / "compose.yaml")) == {"router-0", "recorder-0", "world-0", "observer-0", "lidar-0",
                                                                 "lidar-1", "learner-0", "learner-1"}
    (tmp_path / "compose.yaml").write_text("services:\n  start: {}\n  router: {}\n  learner: {}\n  up: {}\n")
    assert compose_identities(1, tmp_path / "compose.yaml") == ["router-0", "learner-0"]  # what the file runs, no tool
    assert "status-0" not in compose_identities(1, tmp_path / "none.yaml") and "learner-0" in compose_identities(1, tmp_path / "x")


def test_the_start_sees_when_no_service_runs_any_more(tmp_path):
    running = tmp_path / "running"
    assert not nobody_running(running)  # no service has ever started: not "over"
    with open(running, "a") as service:  # what each service's entrypoint holds while it runs
        fcntl.flock(service, fcntl.LOCK_SH)
        assert not nobody_running(running)
    assert nobody_running(running)
