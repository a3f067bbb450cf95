"""``docker compose up`` on a real Docker engine, with the run's credentials from ``swarmmap
secrets`` (every link mutual TLS): the run ends by itself with the recorder's status, the run
directory is whole and owned by the invoking user, and the recording shows every robot; the
image builds behind a TLS-intercepting proxy when given the site's CA."""

from __future__ import annotations

import json
import os
import subprocess

import pytest

from tests.conftest import REPO, recording_entities
from tests.deploy.conftest import BASE_IMAGE, build_context, compose_command

pytestmark = pytest.mark.deploy

UID = GID = 4321  # someone who is not root


def test_compose_up_returns_by_itself_with_a_whole_run_directory(docker_engine, tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    os.chown(runs, UID, GID)
    env = os.environ | {"BASE_IMAGE": BASE_IMAGE, "SWARMMAP_UID": str(UID), "SWARMMAP_GID": str(GID),
                        "SWARMMAP_RUNS": str(runs), "SWARMMAP_RUN_ID": "compose"}
    compose = [*compose_command(), "-f", str(REPO / "compose.yaml"), "-p", f"swarmmaptest{os.getpid()}"]
    try:
        build = subprocess.run([*compose, "build"], cwd=REPO, env=env, capture_output=True, text=True, timeout=1500)
        assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
        secrets = subprocess.run([*compose, "run", "--rm", "recorder", "secrets"], cwd=REPO, env=env, capture_output=True,
                                 text=True, timeout=300)
        assert secrets.returncode == 0, secrets.stdout[-3000:] + secrets.stderr[-3000:]
        up = subprocess.run([*compose, "up", "--exit-code-from", "recorder"], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=900)
    finally:
        subprocess.run([*compose, "down", "--remove-orphans"], cwd=REPO, env=env, capture_output=True, timeout=300)
    assert up.returncode == 0, up.stdout[-5000:] + up.stderr[-2000:]
    run_dir = runs / "compose"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"], summary
    assert all(v["finished"] and v["rounds"] == 60 for v in summary["learners"].values())
    for name in ("config.yaml", "metrics.csv", "groundtruth.png", "groundtruth.npz", "observer.json", "recording.rrd"):
        assert (run_dir / name).stat().st_size > 0, name
    for robot in range(3):
        for name in (f"maps/robot-{robot}-mean.png", f"models/robot-{robot}.pt", f"data/robot-{robot}.npz"):
            assert (run_dir / name).exists(), name
    assert (run_dir / "secrets" / "learner-2.pem").exists() and "INSECURE" not in up.stdout + up.stderr
    owners = {(p.stat().st_uid, p.stat().st_gid) for p in run_dir.rglob("*")}
    assert owners == {(UID, GID)}, f"files owned by {owners}"
    entities = recording_entities(run_dir / "recording.rrd")
    for robot in range(3):
        assert {f"/world/robots/{robot}/pose", f"/world/robots/{robot}/scan", f"/maps/mean/robot-{robot}"} <= entities.keys()


def untrusting_base() -> str:
    """The kit's base image without the machine's CA: pip there meets the proxy's certificate."""
    tag = "swarmmap-test/untrusting:latest"
    dockerfile = f'FROM {BASE_IMAGE}\nENV PIP_CERT="" REQUESTS_CA_BUNDLE=""\nRUN rm -f /usr/local/share/host-ca.crt\n'
    subprocess.run(["docker", "build", "-q", "-t", tag, "-"], input=dockerfile, text=True, check=True,
                   capture_output=True, timeout=300)
    return tag


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
