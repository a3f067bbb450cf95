"""``docker compose up`` on a real Docker engine, in a fresh copy of the repository owned by a user
who is not root, with nothing set beforehand: the run is secure (every link mutual TLS, each
container holding only its own key, signed by the start of the run, which keeps the CA key in
memory; each service's container mounts its own run only), ends by itself and is whole and
owned by that user; then, in the same clone, ``SWARMMAP_ROBOTS=5 docker compose up --exit-code-from recorder``
on the same run id is refused, the finished run left as it was, and under another run id runs
five exploring robots (replicas of one service that claim their ids, which a restarted container keeps)
and returns the recorder's status; a run directory holding an unfinished run with other
settings is refused, resumed or not, and left as it was, and no container of the refused run
stays up. A run on a real LiDAR log reads it from the data folder (SWARMMAP_DATA, mounted
read-only in start and world only). The image also builds behind a TLS-intercepting proxy when given
the site's CA."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import KIT_DATA, REPO, SWARMMAP, clean_env, free_port, recording_entities, wait_until
from tests.deploy.conftest import BASE_IMAGE, build_context, compose_command

pytestmark = pytest.mark.deploy

UID = GID = 4321  # someone who is not root
PROJECT = "swarmmaptest"
# What a fresh shell would not have: settings that would make this run differ from a user's.
NOT_SET = ("BASE_IMAGE", "TORCH", "CA_BUNDLE")


@pytest.fixture(scope="module")
def clone(docker_engine, tmp_path_factory) -> Path:
    """The files of a fresh clone that compose uses, owned by UID:GID, and their images (built
    as `up` builds them on a fresh clone: from .env's settings); compose's containers, network
    and volume are removed afterwards."""
    dest = build_context(tmp_path_factory.mktemp("clone") / "swarmmap")
    for name in ("compose.yaml", ".env"):
        shutil.copy(REPO / name, dest / name)
    for path in [dest, *dest.rglob("*")]:
        os.lchown(path, UID, GID)
    build = compose(dest, "build")  # this project's images of an earlier session hold older code
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    yield dest
    compose(dest, "down", "--remove-orphans", "--volumes", timeout=300)


def compose(clone: Path, *args: str, env: dict[str, str] | None = None, timeout: float = 2400) -> subprocess.CompletedProcess:
    """``docker compose ARGS`` in ``clone`` with this process's environment less any swarmmap
    setting, plus ``env``; the observer's ports are free ones."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("SWARMMAP_") and k not in NOT_SET}
    ports = {"SWARMMAP_VIEWER_PORT": str(free_port()), "SWARMMAP_VIEWER_GRPC_PORT": str(free_port())}
    return subprocess.run([*compose_command(), "-p", PROJECT, *args], cwd=clone, env=base | ports | (env or {}),
                          capture_output=True, text=True, timeout=timeout)


def output(proc: subprocess.CompletedProcess, clone: Path, env: dict[str, str] | None = None) -> str:
    """What compose said, and the start's and recorder's last words (a refused start is only in its log)."""
    logs = compose(clone, "logs", "--no-color", "--tail", "20", "start", "recorder", env=env, timeout=120).stdout
    return proc.stdout[-6000:] + proc.stderr[-3000:] + "\nstart, recorder:\n" + logs


def assert_whole_run(run_dir: Path, robots: int, rounds: int) -> None:
    """summary.json ok with every learner finished, metrics rows for every robot, every output."""
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"], summary
    assert {k: (v["finished"], v["rounds"]) for k, v in summary["learners"].items()} == {
        str(r): (True, rounds) for r in range(robots)}
    with (run_dir / "metrics.csv").open() as f:
        assert {int(row["robot"]) for row in csv.DictReader(f)} == set(range(robots))
    for name in ("config.yaml", "groundtruth.png", "groundtruth.npz", "observer.json", "recording.rrd"):
        assert (run_dir / name).stat().st_size > 0, name
    for robot in range(robots):
        for name in (f"maps/robot-{robot}-mean.png", f"models/robot-{robot}.pt", f"data/robot-{robot}.npz"):
            assert (run_dir / name).exists(), name
    assert not [p for p in run_dir.rglob("*") if p.is_file() and b"PRIVATE KEY" in p.read_bytes()], "a private key in the run"
    entities = recording_entities(run_dir / "recording.rrd")
    for robot in range(robots):
        assert {f"/world/robots/{robot}/pose", f"/world/robots/{robot}/scan", f"/maps/mean/robot-{robot}"} <= entities.keys()


def logged_robots(container: str) -> list[str]:
    """The robot ids a lidar or learner container's log says it serves, one per start."""
    logs = subprocess.run(["docker", "logs", container], capture_output=True, text=True, timeout=60)
    return [line.split("serves robot ")[1].split()[0] for line in (logs.stdout + logs.stderr).splitlines() if "serves robot " in line]


def running() -> list[str]:
    """The names of this project's containers that are running."""
    ps = subprocess.run(["docker", "ps", "--filter", f"label=com.docker.compose.project={PROJECT}", "--format", "{{.Names}}"],
                        capture_output=True, text=True, timeout=60)
    return ps.stdout.split()


def containers(clone: Path) -> dict[str, str]:
    """This project's containers (running or not): id -> compose service."""
    ids = compose(clone, "ps", "-a", "-q", timeout=120).stdout.split()
    return {c: inspect(c, '{{index .Config.Labels "com.docker.compose.service"}}') for c in ids}


def inspect(container: str, template: str) -> str:
    return subprocess.run(["docker", "inspect", "-f", template, container], capture_output=True, text=True, timeout=60,
                          check=True).stdout.strip()


def private_keys(container: str, folder: str) -> list[str]:
    """The files holding a private key under ``folder`` in ``container``'s own file system (it may have exited)."""
    copy = subprocess.run(["docker", "cp", f"{container}:{folder}", "-"], capture_output=True, timeout=120)
    if copy.returncode != 0:
        return []
    with tarfile.open(fileobj=io.BytesIO(copy.stdout)) as tar:
        return [m.name for m in tar.getmembers() if m.isfile() and b"PRIVATE KEY" in tar.extractfile(m).read()]


def assert_each_container_holds_its_own_key_only(clone: Path, runs: Path) -> None:
    """Every service's container holds exactly one key, of an identity no other holds; none but
    `start` mounts more than its own run and the two shared volumes, or writes the `compose` one
    (the start's verdict, the CA certificate and the certificates); no shared volume holds a key."""
    held: dict[str, str] = {}
    for container, service in containers(clone).items():
        mounts = json.loads(inspect(container, "{{json .Mounts}}"))
        where = {m["Destination"]: m.get("Source", "") for m in mounts}
        writable = {m["Destination"] for m in mounts if m.get("RW")}
        keys = private_keys(container, "/tmp/swarmmap-credentials")
        if service == "start":
            assert keys == [] and set(where) == {"/runs", "/compose", "/claims", "/etc/swarmmap/compose.yaml", "/data"}, (where, keys)
            assert writable == {"/runs", "/compose", "/claims"}, writable
            continue
        data = {"/data"} if service == "world" else set()  # the world alone reads a log or plan file
        assert set(where) == {"/runs/compose", "/compose", "/claims"} | data and Path(where["/runs/compose"]) == runs / "compose", where
        assert writable == {"/runs/compose", "/claims"}, f"{service} {container} may write {writable}"
        assert len(keys) == 1 and keys[0].endswith("@compose/key.pem"), f"{service} {container} holds {keys}"
        identity = keys[0].split("/")[-2]
        assert identity.split("-")[0] == service and identity not in held, (identity, held)
        held[identity] = container
    image = inspect(next(iter(containers(clone))), "{{.Image}}")
    for volume in ("compose", "claims"):
        shared = subprocess.run(["docker", "run", "--rm", "--entrypoint", "grep", "-v", f"{PROJECT}_{volume}:/c", image,
                                 "-rl", "PRIVATE KEY", "/c"], capture_output=True, text=True, timeout=120)
        assert shared.stdout.strip() == "", f"private keys in the shared volume {volume}: {shared.stdout}"


def owners(folder: Path) -> set[tuple[int, int]]:
    return {(p.stat().st_uid, p.stat().st_gid) for p in [folder, *folder.rglob("*")]}


@pytest.mark.timeout(5400)
def test_up_alone_then_five_robots_from_the_environment_in_the_same_clone(clone):
    up = compose(clone, "up")
    assert up.returncode == 0, output(up, clone)
    assert "INSECURE" not in up.stdout + up.stderr
    runs = clone / "runs"
    assert_whole_run(runs / "compose", robots=3, rounds=60)
    assert owners(runs) == {(UID, GID)}, f"files owned by {owners(runs)}"
    assert_each_container_holds_its_own_key_only(clone, runs)

    finished = {p: p.read_bytes() for p in (runs / "compose").rglob("*") if p.is_file()}
    again = compose(clone, "up", "--exit-code-from", "recorder", env={"SWARMMAP_ROBOTS": "5"})
    assert again.returncode != 0, output(again, clone)
    logs = compose(clone, "logs", "start").stdout
    assert "/runs/compose holds a finished run (it ended " in logs, logs[-3000:]
    assert "never overwritten; choose another SWARMMAP_RUN_ID" in logs, logs[-3000:]
    assert {p: p.read_bytes() for p in (runs / "compose").rglob("*") if p.is_file()} == finished
    five = {"SWARMMAP_ROBOTS": "5", "SWARMMAP_RUN_ID": "five", "SWARMMAP_EXPLORE__POLICY": "frontier",  # exploring,
            "SWARMMAP_LEARNER_MEMORY": "448m", "SWARMMAP_LEARNER_CPUS": "0.4",  # on a robot's budget
            "SWARMMAP_LIDAR_MEMORY": "160m", "SWARMMAP_LIDAR_CPUS": "0.1"}
    up = compose(clone, "up", "--exit-code-from", "recorder", env=five)
    assert up.returncode == 0, output(up, clone, five)
    assert_whole_run(runs / "five", robots=5, rounds=60)
    ex = json.loads((runs / "five" / "summary.json").read_text())["exploration"]
    assert ex["policy"] == "frontier" and ex["final_coverage"] > 0.5 and len(ex["robot_distance_m"]) == 5, ex
    goals = (runs / "five" / "goals.csv").read_text().splitlines()
    assert {line.split(",")[0] for line in goals[1:]} == {str(r) for r in range(5)}, goals
    assert_whole_run(runs / "compose", robots=3, rounds=60)
    assert owners(runs) == {(UID, GID)}, f"files owned by {owners(runs)}"
    learners = compose(clone, "ps", "-a", "-q", "learner", env=five).stdout.split()
    lidars = compose(clone, "ps", "-a", "-q", "lidar", env=five).stdout.split()
    for containers, memory, nano_cpus in ((learners, 448, 400_000_000), (lidars, 160, 100_000_000)):
        for c in containers:  # each robot's containers held to its budget, by the engine
            limits = json.loads(subprocess.run(["docker", "inspect", "--format", "{{json .HostConfig}}", c],
                                               capture_output=True, text=True, check=True, timeout=60).stdout)
            assert (limits["Memory"], limits["NanoCpus"]) == (memory * 1024**2, nano_cpus), (c, limits["Memory"])
    for c in learners:  # and each learner read them and fitted itself
        logs = subprocess.run(["docker", "logs", c], capture_output=True, text=True, timeout=60)
        log = logs.stdout + logs.stderr
        assert "budget: 448 MiB, 0.4 CPU;" in log and "Zenoh shared memory off" in log, log[-2000:]
    served = {c: logged_robots(c) for c in learners}
    assert sorted(r for ids in served.values() for r in ids) == [str(r) for r in range(5)], served
    # A container started again (its host name is its id) serves the robot it served before.
    container = learners[0]
    try:
        subprocess.run(["docker", "start", container], check=True, capture_output=True, timeout=60)
        assert wait_until(lambda: len(logged_robots(container)) == 2, timeout=120, interval=1.0), logged_robots(container)
    finally:
        subprocess.run(["docker", "kill", container], capture_output=True, timeout=60)
    assert logged_robots(container) == served[container] * 2


@pytest.mark.timeout(1800)
def test_a_run_on_a_real_log_reads_it_from_the_data_folder(clone):
    intel = KIT_DATA / "carmen" / "intel-corrected.log.gz"
    if not intel.exists():
        pytest.skip("kit data ../shared/data/carmen not present")
    env = {"SWARMMAP_RUN_ID": "intel", "SWARMMAP_DATA": str(intel.parent), "SWARMMAP_LEARNER__ROUNDS": "20",
           "SWARMMAP_WORLD__DATASET": f"/data/{intel.name}"}
    up = compose(clone, "up", "--exit-code-from", "recorder", env=env)
    assert up.returncode == 0, output(up, clone, env)
    run_dir = clone / "runs" / "intel"
    assert_whole_run(run_dir, robots=3, rounds=20)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["reference"]["kind"] == "log-odds grid of the training scans"
    with np.load(run_dir / "groundtruth.npz") as gt:
        assert "reference" in gt.files and len(gt["val_labels"]) > 1000  # the log's held-out scans


@pytest.mark.timeout(1800)
def test_a_run_directory_holding_an_unfinished_run_with_other_settings_is_refused_and_left_as_it_was(clone):
    other = clone / "runs" / "other"
    prepare = subprocess.run([*SWARMMAP, "prepare", "--preset", "smoke", "--robots", "2", "--run-id", "other", "--run-dir", str(other)],
                             env=clean_env(), capture_output=True, text=True, timeout=120)
    assert prepare.returncode == 0, prepare.stderr
    for path in [other, *other.rglob("*")]:
        os.lchown(path, UID, GID)
    before = {p: p.read_bytes() for p in other.rglob("*") if p.is_file()}
    resume = {"SWARMMAP_RUN_ID": "other", "SWARMMAP_UP__RESUME": "true"}
    up = compose(clone, "up", "--exit-code-from", "recorder", env=resume)
    assert up.returncode != 0, output(up, clone, resume)
    logs = compose(clone, "logs", "start", env=resume).stdout
    assert "robots 2 there, 3 here" in logs and "SWARMMAP_RUN_ID" in logs, logs[-3000:]
    assert wait_until(lambda: not running(), timeout=120, interval=1.0), f"still running: {running()}"
    assert {p: p.read_bytes() for p in other.rglob("*") if p.is_file()} == before


def untrusting_base() -> str:
    """The kit's base image without the machine's CA: pip there meets the proxy's certificate."""
    tag = "swarmmap-test/untrusting:latest"
    dockerfile = f'FROM {BASE_IMAGE}\nENV PIP_CERT="" REQUESTS_CA_BUNDLE=""\nRUN rm -f /usr/local/share/host-ca.crt\n'
    subprocess.run(["docker", "build", "-q", "-t", tag, "-"], input=dockerfile, text=True, check=True,
                   capture_output=True, timeout=300)
    return tag


@pytest.mark.timeout(3600)
def test_image_builds_behind_an_intercepting_proxy_with_the_site_ca_bundle(docker_engine, tmp_path):
    base = untrusting_base()
    ctx = build_context(tmp_path / "ctx", ("/etc/ssl/certs/ca-certificates.crt", "deploy/docker/site-ca.pem"))
    build = ["docker", "build", "-f", "deploy/docker/Dockerfile", "--build-arg", f"BASE_IMAGE={base}"]
    without = subprocess.run([*build, "-t", "swarmmap-test/noca", "."], cwd=ctx, capture_output=True, text=True, timeout=900)
    assert without.returncode != 0, "the build should fail without the site's CA (is PyPI intercepted here?)"
    assert "certificate" in (without.stdout + without.stderr).lower()
    with_ca = subprocess.run([*build, "--build-arg", "CA_BUNDLE=deploy/docker/site-ca.pem", "-t", "swarmmap-test/ca", "."],
                             cwd=ctx, capture_output=True, text=True, timeout=1500)
    assert with_ca.returncode == 0, with_ca.stdout[-3000:] + with_ca.stderr[-3000:]
    out = subprocess.run(["docker", "run", "--rm", "swarmmap-test/ca", "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "recorder" in out.stdout
