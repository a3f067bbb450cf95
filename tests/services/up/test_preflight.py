"""``up`` and ``prepare`` refuse what they can check before anything starts, in seconds, naming
the value and the fix, and create nothing (no run directory, no credentials)."""

from __future__ import annotations

import os
import subprocess
import time

import numpy as np
import pytest

from swarmmap.services.up.preflight import check_run, device_problem, endpoint_problem
from swarmmap.shared.run.config import ConfigError, resolve
from tests.conftest import PROMPT_S, SWARMMAP, clean_env

pytestmark = pytest.mark.timeout(120)


def swarmmap(*args: str, cwd, env: dict | None = None) -> tuple[subprocess.CompletedProcess, float]:
    start = time.monotonic()
    proc = subprocess.run([*SWARMMAP, *args], capture_output=True, text=True, timeout=60, cwd=cwd,
                          env={**clean_env(), **(env or {})})
    return proc, time.monotonic() - start


@pytest.mark.parametrize("command", ["up", "prepare"])
@pytest.mark.integration
def test_a_missing_plan_is_refused_in_seconds_and_nothing_is_created(tmp_path, command):
    proc, took = swarmmap(command, "--floorplan", "missing.svg", "--run-dir", str(tmp_path / "run"), cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert took < PROMPT_S, f"{command} took {took:.1f} s to refuse"
    assert "world.floorplan: missing.svg: file does not exist" in proc.stderr and "procedural" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert sorted(os.listdir(tmp_path)) == [], "something was created before the refusal"


@pytest.mark.integration
def test_a_misspelt_environment_variable_stops_up_naming_it(tmp_path):
    proc, took = swarmmap("up", "--preset", "smoke", cwd=tmp_path, env={"SWARMMAP_LERNER__ROUNDS": "3"})
    assert proc.returncode == 2 and took < PROMPT_S
    assert "SWARMMAP_LERNER__ROUNDS" in proc.stderr and "SWARMMAP_LEARNER__ROUNDS" in proc.stderr
    assert not (tmp_path / "runs").exists()


def prepared(tmp_path, **overrides):
    doc = {"preset": "smoke", "run_dir": str(tmp_path / "run"), **overrides}
    return resolve(doc, environ={})


def test_fewer_waypoint_paths_than_robots_are_refused_naming_the_fix(tmp_path):
    folder = tmp_path / "paths"
    folder.mkdir()
    plan_cfg = prepared(tmp_path)
    facts = check_run(plan_cfg, endpoints=True)  # the plan's own paths, to write as waypoint files
    assert len(facts.path_lengths_m) == 3 and 0 < facts.coverage <= 1 and facts.expected_scans > 0
    from swarmmap.shared.world.plans import load_floorplan, robot_paths

    plan = load_floorplan("procedural", plan_cfg.world, plan_cfg.seed)
    for i, path in enumerate(robot_paths(plan_cfg, plan, plan.occupancy(plan_cfg.world.grid_resolution_m))[:2]):
        np.save(folder / f"{i}.npy", path)
    cfg = prepared(tmp_path, world={"waypoints": str(folder)})
    with pytest.raises(ConfigError, match=r"world.waypoints: .*2 waypoint paths for 3 robots: run at most 2 robots"):
        check_run(cfg, endpoints=True)
    assert check_run(prepared(tmp_path, robots=2, world={"waypoints": str(folder)}), endpoints=True).waypoints == str(folder)
    with pytest.raises(ConfigError, match="world.waypoints: .*waypoint folder does not exist"):
        check_run(prepared(tmp_path, world={"waypoints": str(tmp_path / "nope")}), endpoints=True)


def test_a_device_this_machine_lacks_is_refused():
    import torch

    assert device_problem("learner.device", "auto") is None and device_problem("learner.device", "cpu") is None
    assert "not a torch device" in device_problem("learner.device", "gpu")
    if torch.cuda.is_available():
        assert "CUDA device(s)" in device_problem("learner.device", f"cuda:{torch.cuda.device_count()}")
        assert device_problem("learner.device", "cuda:0") is None
    else:
        assert "no CUDA device" in device_problem("observer.device", "cuda")


def test_endpoints_that_do_not_parse_are_refused():
    assert endpoint_problem("zenoh.connect", "tcp/10.0.0.5:7447") is None
    assert endpoint_problem("zenoh.listen", "tcp/[::1]:0") is None
    assert "not an endpoint" in endpoint_problem("zenoh.connect", "10.0.0.5")
    assert "port 0-65535" in endpoint_problem("zenoh.connect", "tcp/10.0.0.5:99999")
    assert "did you mean 'tcp'" in endpoint_problem("zenoh.connect", "tpc/10.0.0.5:7447")


def test_every_problem_is_reported_at_once_and_nothing_is_written(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    cfg = prepared(tmp_path, run_dir=str(blocker / "run"), zenoh={"connect": ["10.0.0.5"]},
                   learner={"device": "gpu"}, world={"floorplan": str(tmp_path / "plan.svg")})
    with pytest.raises(ConfigError) as info:
        check_run(cfg, endpoints=True)
    text = info.value.message
    for what in ("zenoh.connect", "learner.device", "run_dir", "world.floorplan"):
        assert f"  {what}: " in text, text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]


@pytest.mark.integration
def test_prepare_refuses_an_endpoint_and_writes_no_config(tmp_path):
    proc, took = swarmmap("prepare", "--preset", "smoke", "--run-dir", str(tmp_path / "run"), "--zenoh-connect", "router:7447",
                          cwd=tmp_path)
    assert proc.returncode == 2 and took < PROMPT_S and "zenoh.connect: 'router:7447'" in proc.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("command", [("up",), ("prepare",), ("recorder", "--zenoh-insecure")])
@pytest.mark.integration
def test_a_read_only_run_directory_is_refused_at_start_naming_it(tmpfs, tmp_path, command):
    """Root too: a read-only disk is found by writing, not by asking for permissions."""
    ro = tmpfs("1m", read_only=True)
    proc, took = swarmmap(*command, "--preset", "smoke", "--run-dir", str(ro / "run"), cwd=tmp_path)
    assert proc.returncode == 2 and took < PROMPT_S, proc.stderr[-2000:]
    assert f"run_dir: {ro} cannot be written (Read-only file system)" in proc.stderr and "Traceback" not in proc.stderr
