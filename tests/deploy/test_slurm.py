"""The SLURM job scripts on a real cluster: ``team.sbatch`` runs one task per service and ends
COMPLETED with a whole run directory, and a second job on that run directory is refused; a
killed learner task ends it FAILED within a minute, naming the learner; ``swarmmap-up.sbatch``
runs ``swarmmap up`` as one task (the kit's one-node cluster); and ``team.sbatch`` spreads its
tasks over the three nodes of ``deploy/slurm/local-cluster.sh 3``, a router per host linked in a
ring."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest
from cryptography import x509

from swarmmap.shared.wire.services import identities
from tests.conftest import REPO, recording_entities, wait_until
from tests.deploy.conftest import VENV_BIN, run_kit

pytestmark = pytest.mark.deploy


def sbatch(script: str, tmp_path: Path, *args: str, wait: bool = True,
           options: tuple[str, ...] = ()) -> tuple[str, subprocess.CompletedProcess]:
    """Submit ``deploy/slurm/<script>`` (with sbatch ``options``) with this interpreter's ``swarmmap``
    on PATH; the job id and sbatch's result."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SWARMMAP_", "SLURM_"))}
    env |= {"PATH": f"{VENV_BIN}:{env['PATH']}", "SWARMMAP_RUN_DIR": str(tmp_path / "run")}
    cmd = ["sbatch", "--parsable", f"--chdir={tmp_path}", f"--output={tmp_path}/job-%j.out", *(["--wait"] if wait else []),
           *options, str(REPO / "deploy" / "slurm" / script), *args]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    job = proc.stdout.strip().split(";")[0]
    assert job.isdigit(), proc.stdout + proc.stderr
    return job, proc


def job_state(job: str) -> str:
    out = subprocess.run(["scontrol", "show", "job", job], capture_output=True, text=True, timeout=30).stdout
    return re.search(r"JobState=(\w+)", out).group(1)


def job_output(tmp_path: Path, job: str) -> str:
    return (tmp_path / f"job-{job}.out").read_text()


def test_team_job_runs_a_task_per_service_and_completes(slurm_cluster, tmp_path):
    """An exploring team: the world drives where the learners' goals say, each service a task."""
    job, proc = sbatch("team.sbatch", tmp_path, "--preset", "smoke", "--robots", "3", "--explore", "frontier")
    out = job_output(tmp_path, job)
    assert proc.returncode == 0 and job_state(job) == "COMPLETED", out
    assert "run succeeded: all 3 learners finished" in out
    run_dir = tmp_path / "run"
    logs = sorted(p.stem for p in (run_dir / "logs").glob("*.log"))
    # One log per SLURM task (srun --output .../<service>-%t.log): a task per service.
    assert logs == ["learner-0", "learner-1", "learner-2", "lidar-0", "lidar-1", "lidar-2", "observer-0", "recorder-0",
                    "router-0", "world-0"]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["run_id"] == f"slurm-{job}"
    learners = summary["learners"].values()
    assert all(v["finished"] and v["rounds"] == 60 for v in learners)
    assert len({v["reported_pid"] for v in learners}) == 3
    ex = summary["exploration"]
    assert ex["policy"] == "frontier" and ex["final_coverage"] > 0.5 and all(d > 1.0 for d in ex["robot_distance_m"].values()), ex
    goals = (run_dir / "goals.csv").read_text().splitlines()
    assert {line.split(",")[0] for line in goals[1:]} == {"0", "1", "2"}, goals  # every learner's goals reached the world
    for name in ("config.yaml", "metrics.csv", "groundtruth.npz", "observer.json", "recording.rrd"):
        assert (run_dir / name).stat().st_size > 0, name
    entities = recording_entities(run_dir / "recording.rrd")
    assert all(f"/world/robots/{r}/pose" in entities and f"/maps/mean/robot-{r}" in entities for r in range(3))
    # Each service's key in a folder of its own (the router's certificate names the job's node); no CA key.
    keys = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.rglob("*") if p.is_file() and b"PRIVATE KEY" in p.read_bytes())
    assert keys == sorted(f"secrets/{name}@slurm-{job}/key.pem" for name in identities(3)), keys
    # The same run directory again: refused, resumed or not, and nothing of the finished run changes.
    kept = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    for extra in ((), ("--resume",)):
        again, proc = sbatch("team.sbatch", tmp_path, "--preset", "smoke", "--robots", "3", *extra)
        out = job_output(tmp_path, again)
        assert job_state(again) == "FAILED" and f"{run_dir} holds a finished run (it ended " in out, out
        assert "never overwritten" in out and "SWARMMAP_RUN_DIR" in out, out
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == kept


def srun_commands() -> list[list[str]]:
    """The command lines of the srun processes running now."""
    out = []
    for proc in Path("/proc").iterdir():
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if argv and argv[0].endswith(b"srun"):
            out.append([a.decode(errors="replace") for a in argv])
    return out


def test_team_job_asks_slurm_for_each_robots_budget_and_its_learners_fit_it(slurm_cluster, tmp_path):
    """``--budget 512M,0.5``: each robot's learner step asks for the budget less its lidar's share,
    on one whole CPU, its lidar step for the rest; the learners fit the budget; one too small is
    refused at the start of the job, naming the smallest that fits."""
    job, _ = sbatch("team.sbatch", tmp_path, "--preset", "smoke", "--robots", "2", "--rounds", "20", "--budget", "512M,0.5",
                    wait=False)
    asked: dict[str, set[str]] = {}

    def steps_seen() -> bool:
        for argv in srun_commands():
            if "learner" in argv or "lidar" in argv:
                kind = "learner" if "learner" in argv else "lidar"
                asked.setdefault(kind, set()).update(a for a in argv if a.startswith("--mem-per-cpu"))
        return set(asked) == {"learner", "lidar"}

    try:
        assert wait_until(steps_seen, 300, 0.5), asked
    finally:
        assert wait_until(lambda: job_state(job) not in ("RUNNING", "COMPLETING", "PENDING", "CONFIGURING"), 600, 1)
    out = job_output(tmp_path, job)
    assert job_state(job) == "COMPLETED", out
    assert asked == {"learner": {"--mem-per-cpu=384M"}, "lidar": {"--mem-per-cpu=128M"}}, asked
    assert "robot 1's budget: learner 384 MiB on 1 CPU(s), lidar 128 MiB" in out
    for robot in (0, 1):
        log = (tmp_path / "run" / "logs" / f"learner-{robot}.log").read_text()
        assert f"robot {robot}'s budget: 512 MiB, 0.5 CPU;" in log, log[-2000:]
    small = tmp_path / "small"
    small.mkdir()
    job, _ = sbatch("team.sbatch", small, "--preset", "smoke", "--robots", "2", "--budget", "200M,0.5")
    out = job_output(small, job)
    assert job_state(job) == "FAILED" and "The smallest budget that fits: --budget" in out, out


def learner_pid(run_dir: Path, robot: int) -> int | None:
    """The pid of the learner task of ``robot`` (its SLURM_PROCID) of the run in ``run_dir``."""
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
            env = (proc / "environ").read_bytes().split(b"\0")
        except (OSError, PermissionError):
            continue
        if b"learner" in cmd and any(str(run_dir).encode() in c for c in cmd) and f"SLURM_PROCID={robot}".encode() in env:
            return int(proc.name)
    return None


def test_killing_a_learner_task_fails_the_job_within_a_minute_naming_it(slurm_cluster, tmp_path):
    job, _ = sbatch("team.sbatch", tmp_path, "--preset", "smoke", "--robots", "3", "--rounds", "100000", wait=False)
    try:
        recorder_log = tmp_path / "run" / "logs" / "recorder-0.log"
        assert wait_until(lambda: recorder_log.exists() and "round   10" in recorder_log.read_text(), 300, 0.5), \
            job_output(tmp_path, job)
        pid = learner_pid(tmp_path / "run", 1)
        assert pid is not None, "no learner task with SLURM_PROCID=1"
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        assert wait_until(lambda: job_state(job) not in ("RUNNING", "COMPLETING", "PENDING"), 60, 0.5)
        assert time.monotonic() - killed < 60
    finally:
        subprocess.run(["scancel", job], capture_output=True, timeout=30)
    assert job_state(job) == "FAILED"
    out = job_output(tmp_path, job)
    assert "run FAILED: learner 1 left before finishing" in out, out
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert not summary["ok"] and "learner 1" in summary["reason"]


def test_single_node_up_job_completes(slurm_cluster, tmp_path):
    job, proc = sbatch("swarmmap-up.sbatch", tmp_path, "--preset", "smoke", "--robots", "2", "--rounds", "10")
    assert proc.returncode == 0 and job_state(job) == "COMPLETED", job_output(tmp_path, job)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["ok"] and summary["status"] == 0


@pytest.fixture
def three_nodes():
    """The three-node cluster of ``deploy/slurm/local-cluster.sh``; the kit's one-node cluster back after."""
    run_kit("slurm-local.sh")  # the packages and munge (and a skip or failure where this machine cannot)
    script = REPO / "deploy" / "slurm" / "local-cluster.sh"
    proc = subprocess.run(["bash", str(script), "3"], capture_output=True, text=True, timeout=600)
    try:
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
        yield
    finally:
        subprocess.run(["bash", str(script), "stop"], capture_output=True, text=True, timeout=120)
        run_kit("slurm-local.sh")


def router_pid(run_dir: Path, ident: str) -> int | None:
    """The pid of the router ``--ident IDENT`` of the run in ``run_dir`` (the task, not its srun)."""
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except (OSError, PermissionError):
            continue
        if not cmd[0].endswith(b"srun") and b"router" in cmd and any(str(run_dir).encode() in c for c in cmd) and ident.encode() in cmd:
            return int(proc.name)
    return None


def test_team_job_spreads_its_tasks_over_three_nodes_and_completes(three_nodes, tmp_path):
    """A robot on each node beside a router of its own, the routers in a ring; robot 1's router
    killed mid-run is started again and the run completes."""
    job, _ = sbatch("team.sbatch", tmp_path, "--preset", "smoke", "--robots", "3", options=("--nodes", "3"), wait=False)
    run_dir = tmp_path / "run"
    try:
        recorder_log = run_dir / "logs" / "recorder-0.log"
        assert wait_until(lambda: recorder_log.exists() and "round   10" in recorder_log.read_text(), 600, 0.5), \
            job_output(tmp_path, job)
        pid = router_pid(run_dir, "r1")
        assert pid is not None, "no router with --ident r1"
        os.kill(pid, signal.SIGKILL)
        assert wait_until(lambda: job_state(job) not in ("RUNNING", "COMPLETING", "PENDING", "CONFIGURING"), 900, 1)
    finally:
        subprocess.run(["scancel", job], capture_output=True, timeout=30)
    out = job_output(tmp_path, job)
    assert job_state(job) == "COMPLETED", out
    assert "3 robots on 3 node(s) (swarm-node[1-3]), a router per host in a ring" in out, out
    assert "router-r1 (a host's router) exited with status" in out and "starting it again (1 of 3)" in out, out
    assert "run succeeded: all 3 learners finished" in out, out
    where = {}
    for log in sorted((run_dir / "logs").glob("*.log")):  # each task says where it ran
        found = re.search(rf"SLURM job {job}, task \d+, on node (swarm-node\d)", log.read_text())
        assert found, f"{log.name} names no node"
        where[log.stem] = found[1]
    # The base services beside the first node's router; each robot's beside a router of its own.
    assert sorted(where) == sorted(["router-0", "recorder-0", "observer-0", "world-0"] +
                                   [f"{s}{r}" for s in ("router-r", "learner-", "lidar-") for r in range(3)]), where
    assert {where[s] for s in ("router-0", "recorder-0", "observer-0", "world-0")} == {"swarm-node1"}, where
    assert {where[f"learner-{r}"] for r in range(3)} == {"swarm-node1", "swarm-node2", "swarm-node3"}, where
    assert all(where[f"learner-{r}"] == where[f"lidar-{r}"] == where[f"router-r{r}"] for r in range(3)), where
    # The routers in a ring: each dials the next host's router by its node's name.
    ring = ["router-0", "router-r0", "router-r1", "router-r2", "router-0"]
    for a, b in zip(ring, ring[1:]):
        line = next(x for x in (run_dir / "logs" / f"{a}.log").read_text().splitlines() if " up, listening on " in x)
        assert f"linking to tls/{where[b]}:" in line, (a, b, line)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and all(v["finished"] and v["rounds"] == 60 for v in summary["learners"].values())
    # A certificate per router, each naming every node (the others dial it by its node's name).
    for name in ("router-0", "router-r0", "router-r1", "router-r2"):
        cert = x509.load_pem_x509_certificate((run_dir / "secrets" / f"{name}@slurm-{job}" / "cert.pem").read_bytes())
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(x509.DNSName)
        assert {"swarm-node1", "swarm-node2", "swarm-node3"} <= set(names), (name, names)
