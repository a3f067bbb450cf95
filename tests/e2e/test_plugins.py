"""Plug-ins from a package outside swarmmap, installed with pip into a fresh virtual environment:
a consensus rule and a dataset reader chosen by name in a whole run over Zenoh, a service that
gets its identity, access rules, command, place in ``up`` and in the SLURM job, all listed by
``swarmmap plugins``; broken ones refused by name in seconds. No file of swarmmap changes."""

from __future__ import annotations

import json
import site
import subprocess
import sys
import time

import numpy as np
import pytest

from swarmmap.shared.learning.networks import load_model
from swarmmap.shared.world.datasets import read_log
from tests.conftest import KIT_DATA, REPO, clean_env

pytestmark = pytest.mark.e2e
FIXTURES = REPO / "tests" / "fixtures"
INTEL = KIT_DATA / "carmen" / "intel-corrected.log.gz"


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    """A new virtual environment that sees swarmmap and its dependencies where this one has them
    (a .pth adds this environment's site-packages) and has the two plug-in packages pip-installed."""
    root = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True)
    python = root / "bin" / "python"
    own = subprocess.run([str(python), "-c", "import site; print(site.getsitepackages()[0])"], capture_output=True,
                         text=True, check=True).stdout.strip()
    outer = [p for p in site.getsitepackages() if p.endswith("site-packages")][0]
    (root / "lib" / own.split("/lib/", 1)[1] / "swarmmap-env.pth").write_text(f"import site; site.addsitedir({outer!r})\n")
    for package in ("plugin_package", "broken_plugin"):
        proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
                               "--no-build-isolation", "--no-index", str(FIXTURES / package)],
                              capture_output=True, text=True, env=clean_env())
        assert proc.returncode == 0, proc.stderr[-3000:]
    return python


def swarmmap(python, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([str(python), "-m", "swarmmap.services.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=clean_env())


def test_plugins_lists_each_part_with_its_package_and_refuses_the_broken_ones(venv):
    proc = swarmmap(venv, "plugins", timeout=60)
    rows = {line.split()[0]: line for line in proc.stdout.splitlines() if line.startswith("  ")}
    assert "swarmmap-example-plugins 1.2.0" in rows["damped"] and "every pull scaled" in rows["damped"]
    assert "swarmmap-example-plugins 1.2.0" in rows["scans-csv"] and "*.scans.csv" in rows["scans-csv"]
    assert "swarmmap-example-plugins 1.2.0" in rows["heartbeat"] and "hears every learner's Metrics" in rows["heartbeat"]
    assert "swarmmap-example-plugins 1.2.0" in rows["randk"] and "random share" in rows["randk"]
    assert rows["sigma"].split()[1:3] == ["swarmmap", "0.1.0"] and rows["quant"].split()[1:3] == ["swarmmap", "0.1.0"]
    assert "REFUSED" in rows["crashes"] and "failed to import: ImportError" in rows["crashes"]
    assert "breaks its contract" in rows["not-a-rule"] and "swarmmap-broken-plugins 0.0.1" in rows["not-a-rule"]
    assert proc.returncode == 2 and "2 plug-in(s) refused" in proc.stderr


@pytest.mark.parametrize("field, group, rule, why", [
    ("consensus", "consensus", "crashes", "failed to import: ImportError: this rule needs a library"),
    ("consensus", "consensus", "not-a-rule", "breaks its contract: swarmmap_broken_plugins:NOT_A_RULE is a dict"),
    ("compression", "compressions", "no-encoder", "breaks its contract: it made a function, not an Encoder")])
def test_a_run_naming_a_broken_plugin_is_refused_by_name_in_seconds(venv, tmp_path, field, group, rule, why):
    start = time.monotonic()
    proc = swarmmap(venv, "up", "--preset", "smoke", "--set", f"learner.{field}={rule}", "--run-dir", str(tmp_path / "run"),
                    timeout=120)
    took = time.monotonic() - start
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert f"{group} plug-in {rule!r}" in proc.stderr and "swarmmap-broken-plugins 0.0.1" in proc.stderr and why in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "run").exists()
    assert took < 20, f"refused after {took:.1f} s"


def write_scans_csv(log, path, every: int = 2) -> None:
    """The log in the plug-in's format: t, x, y, heading, angle_min, angle_increment, range_max, ranges."""
    step = float(log.angles[1] - log.angles[0])
    rows = [[log.t[i], *log.poses[i], log.angles[0], step, log.no_return_m, *log.ranges[i]] for i in range(0, len(log), every)]
    np.savetxt(path, np.array(rows), delimiter=",", fmt="%.5f", header="t,x,y,heading,angle_min,angle_increment,range_max,ranges")


def test_a_smoke_run_trains_with_the_plugins_rule_on_the_plugins_log(venv, tmp_path):
    if not INTEL.exists():
        pytest.skip("kit data ../shared/data/carmen not present")
    log = tmp_path / "intel.scans.csv"
    write_scans_csv(read_log(INTEL), log)
    run = tmp_path / "run"
    proc = swarmmap(venv, "up", "--preset", "smoke", "--dataset", str(log), "--robots", "3", "--rounds", "20", "--no-observer",
                    "--set", "learner.consensus=damped", "--set", 'learner.consensus_options={"pull": 0.5}', "--run-dir", str(run))
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["ok"] and len(summary["learners"]) == 3
    for v in summary["learners"].values():  # each learner trained over Zenoh with the plug-in's rule, and learned
        assert v["finished"] and v["final_val_bce"] < 0.9 * v["first_val_bce"]
    config = (run / "config.yaml").read_text()
    assert "consensus: damped" in config and "intel.scans.csv" in config
    world = (run / "logs" / "world-0.log").read_text()
    assert "read by the scans-csv reader of swarmmap-example-plugins 1.2.0" in world and "held-out validation set" in world
    learner = (run / "logs" / "learner-0.log").read_text()
    assert "consensus damped" in learner


def test_a_smoke_run_on_a_plan_trains_with_the_plugins_rule_over_zenoh(venv, tmp_path):
    run = tmp_path / "run"
    proc = swarmmap(venv, "up", "--preset", "smoke", "--rounds", "20", "--no-observer", "--set", "learner.consensus=damped",
                    "--set", "learner.compression=randk", "--set", 'learner.compression_options={"share": 0.3}',
                    "--run-dir", str(run))
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["ok"] and all(v["finished"] for v in summary["learners"].values())
    cfg = (run / "config.yaml").read_text()
    assert "transport: zenoh" in cfg and "consensus: damped" in cfg and "compression: randk" in cfg
    log = (run / "logs" / "learner-1.log").read_text()
    assert "consensus damped (from swarmmap-example-plugins 1.2.0)" in log
    assert "compression randk (from swarmmap-example-plugins 1.2.0)" in log
    # the other package's States went as the wire's topk encoding (8 bytes a value kept, 30% of them), not float32
    values = sum(p.numel() for p in load_model(run / "models" / "robot-0.pt").parameters())
    for robot, learner in summary["learners"].items():
        assert learner["bytes_sent"] < 0.75 * 21 * 4 * values, (robot, learner["bytes_sent"], values)
    # up started the other package's service with the run's own: its certificate, its session, what it heard
    assert (run / "secrets" / f"heartbeat-0@{summary['run_id']}" / "cert.pem").exists()
    beat = (run / "logs" / "heartbeat-0.log").read_text()
    assert "heard the metrics of robots [0, 1, 2], last rounds [20, 20, 20]" in beat


def test_a_service_from_another_package_gets_its_identity_rules_command_and_place(venv):
    """Registered by one entry point: the identity and access rules come from its declaration,
    `swarmmap heartbeat` is a command, and the SLURM job (which starts a step per line of
    `swarmmap services --slurm`) and `up` (below) start it."""
    code = ("from swarmmap.shared.wire.protocol import Keys; from swarmmap.shared.wire.secrets import access_policy; "
            "from swarmmap.shared.wire.services import identities; import json; "
            "p = access_policy(Keys('swarmmap', 'r1'), 2); "
            "print(json.dumps([identities(2), [r for r in p['rules'] if r['id'].startswith('heartbeat-0')]]))")
    proc = subprocess.run([str(venv), "-c", code], capture_output=True, text=True, check=True, env=clean_env())
    names, rules = json.loads(proc.stdout)
    assert "heartbeat-0" in names and "heartbeat-1" not in names  # one a run
    receives = next(r for r in rules if r["id"] == "heartbeat-0-receives")["key_exprs"]
    assert "swarmmap/r1/learners/*/metrics" in receives and not any("state" in k or "scan" in k for k in receives)
    speaks = next(r for r in rules if r["id"] == "heartbeat-0-speaks")["key_exprs"]
    assert speaks == ["swarmmap/r1/alive/heartbeat/0"]
    assert "heartbeat one light" in swarmmap(venv, "services", "--slurm", timeout=60).stdout.splitlines()
    help_ = swarmmap(venv, "heartbeat", "--help", timeout=60)
    assert help_.returncode == 0 and "hears every learner's Metrics" in help_.stdout
