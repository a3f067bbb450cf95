"""A team across hosts on one machine (``up --netns``): each robot's services in a network
namespace of its own with its own router, the routers linked in a ring over mutual TLS; a
robot host's router killed, the team cut in two for 60 s; nothing left behind, also after
``kill -9`` of ``up``. Needs root (namespaces, veth, nftables): skipped without, failed under CI."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
from pathlib import Path

import pytest

from tests.conftest import SWARMMAP, clean_env, wait_until
from tests.harness import final_losses, leftovers, reported_round, up

pytestmark = [pytest.mark.e2e, pytest.mark.network]

SMOKE = ["--preset", "smoke", "--robots", "3", "--no-observer", "--netns"]
PARTITION_ROUNDS = 800  # the pair goes on 200-450 rounds in the 60 s apart; then some 150 or more to meet again (docs/deployment.md)


@pytest.fixture(autouse=True)
def needs_root():
    missing = [tool for tool in ("ip", "tc", "nft") if shutil.which(tool) is None]
    why = "network namespaces need root" if os.geteuid() != 0 else (f"{', '.join(missing)} not installed" if missing else None)
    if why and os.environ.get("CI") == "true":
        pytest.fail(f"CI=true: {why}")
    if why:
        pytest.skip(why)


def network(run_dir: Path) -> dict:
    return json.loads((run_dir / "network.json").read_text())


def present_namespaces() -> set[str]:
    return {line.split()[0] for line in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.splitlines()
            if line.strip()}


def left_behind(run_dir: Path) -> list[str]:
    """The run's namespaces and base link still present."""
    net = network(run_dir)
    link = subprocess.run(["ip", "link", "show", f"sm{net['tag']}hb"], capture_output=True).returncode == 0
    return sorted(set(net["namespaces"]) & present_namespaces()) + ([f"sm{net['tag']}hb"] if link else [])


def services_in(namespace: str, config: str) -> set[str]:
    """The run's services whose processes live in ``namespace`` (``ip netns pids``), by name."""
    names = set()
    for pid in subprocess.run(["ip", "netns", "pids", namespace], capture_output=True, text=True).stdout.split():
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        if config in cmd and "swarmmap.services.cli" in cmd:
            service = cmd[cmd.index("swarmmap.services.cli") + 1]
            flag = "--robot" if "--robot" in cmd else "--ident" if "--ident" in cmd else None
            names.add(f"{service}-{cmd[cmd.index(flag) + 1]}" if flag else service)
    return names


def router_pid(run_dir: Path, ident: str) -> int | None:
    config = str(run_dir / "config.yaml")
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        if proc.name.isdigit() and "router" in cmd and config in cmd and "--ident" in cmd and cmd[cmd.index("--ident") + 1] == ident:
            return int(proc.name)
    return None


def final_consensus(run_dir: Path) -> float:
    """The largest consensus error among the robots' final rows."""
    with (run_dir / "metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["final"] in ("1", "True")]
    assert rows, f"no final metrics in {run_dir}"
    return max(float(r["consensus_error"]) for r in rows)


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple[Path, dict[str, set[str]]]:
    """A clean run on namespaces, and which services each robot namespace held while it ran."""
    run_dir = tmp_path_factory.mktemp("netns") / "clean"
    proc = up(run_dir, *SMOKE)
    config, seen = str(run_dir / "config.yaml"), {}
    try:
        assert wait_until(lambda: (run_dir / "network.json").exists(), 120, 0.2), "up wrote no network.json"
        names = network(run_dir)["namespaces"][1:]  # (the switch first)

        def every_robot_in_its_own() -> bool:
            seen.update({ns: services_in(ns, config) for ns in names})
            return all(len(s) == 3 for s in seen.values())
        wait_until(every_robot_in_its_own, 180, 0.5)
        assert proc.wait(600) == 0, Path(f"{run_dir}.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    return run_dir, seen


def test_every_robot_runs_in_a_namespace_of_its_own_and_nothing_is_left(clean):
    run_dir, seen = clean
    net = network(run_dir)
    assert {ns.rsplit("-", 1)[1]: names for ns, names in seen.items()} == {
        f"r{i}": {f"learner-{i}", f"lidar-{i}", f"router-r{i}"} for i in range(3)}
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and sorted(summary["hosts"]) == ["base", "r0", "r1", "r2"]
    assert summary["hosts"]["r1"]["links"] == [f"tls/{net['hosts']['r2']}:7447"]  # the ring: r1 dials r2, over TLS
    assert not left_behind(run_dir) and not leftovers(run_dir)


def test_a_killed_up_leaves_no_namespace_link_or_service(tmp_path):
    run_dir = tmp_path / "killed"
    proc = up(run_dir, *SMOKE, "--rounds", "100000")
    try:
        assert wait_until(lambda: (run_dir / "network.json").exists() and reported_round(run_dir, 0) >= 0, 240, 0.2)
        assert len(left_behind(run_dir)) == 5  # the switch, three robot hosts, the base's link
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert wait_until(lambda: not left_behind(run_dir) and not leftovers(run_dir), 60, 0.5), \
        f"left behind: {left_behind(run_dir)}, processes {leftovers(run_dir)}"
    assert "ended without removing its network" in (run_dir / "logs" / "netns-guard.log").read_text()


@pytest.mark.timeout(900)  # a run with a router killed and back, on a loaded machine past pytest's 300 s
def test_a_robot_hosts_router_killed_the_robot_rejoins_and_the_team_ends_as_clean(clean, tmp_path):
    run_dir = tmp_path / "router-killed"
    proc = up(run_dir, *SMOKE)
    try:
        assert wait_until(lambda: reported_round(run_dir, 1) >= 10 and router_pid(run_dir, "r1"), 300, 0.05)
        os.kill(router_pid(run_dir, "r1"), signal.SIGKILL)
        assert proc.wait(600) == 0, Path(f"{run_dir}.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["services"]["router-r1"]["restarts"] == 1
    assert [a["robot"] for a in summary["absences"]] == [1] and summary["absences"][0]["back_after_s"] is not None
    reference = final_losses(clean[0])
    for robot, loss in final_losses(run_dir).items():
        assert abs(loss - reference[robot]) <= 0.05 * reference[robot], f"robot {robot}: {loss:.4f} against {reference[robot]:.4f}"


@pytest.mark.timeout(1500)  # two runs of 800 rounds, one of them a minute apart: past pytest's 300 s when loaded
def test_a_team_cut_in_two_for_a_minute_meets_again(tmp_path):
    clean_dir, cut_dir = tmp_path / "clean", tmp_path / "cut"
    rounds = ["--rounds", str(PARTITION_ROUNDS)]
    assert up(clean_dir, *SMOKE, *rounds).wait(600) == 0
    proc = up(cut_dir, *SMOKE, *rounds)
    try:
        assert wait_until(lambda: reported_round(cut_dir, 2) >= 10, 300, 0.05)
        cut = subprocess.run([*SWARMMAP, "net", str(cut_dir), "cut", "r1", "r2", "--for", "60"], env=clean_env(),
                             capture_output=True, text=True, timeout=120)
        assert cut.returncode == 0, cut.stderr
        assert "cut: r1 r2 | base r0" in cut.stderr and "healed" in cut.stderr
        assert proc.wait(900) == 0, Path(f"{cut_dir}.up.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((cut_dir / "summary.json").read_text())
    away = {a["robot"]: a for a in summary["absences"]}
    assert sorted(away) == [1, 2] and all(a["back_after_s"] >= 30 for a in away.values()), summary["absences"]
    learner0 = (cut_dir / "logs" / "learner-0.log").read_text()
    # (a State of the team's round, far ahead, is refused until a second neighbour vouches for it: not a judgement of it)
    refusals = [line for line in learner0.splitlines() if "refused the state" in line and "while this node is at round" not in line]
    assert "neighbour 1 left" in learner0 and not refusals, refusals
    # the two halves learnt apart for a minute; their final maps agree as a clean run's do
    assert final_consensus(cut_dir) <= 1.5 * final_consensus(clean_dir) + 0.005, \
        (final_consensus(cut_dir), final_consensus(clean_dir))
    # and they map about as well as the clean team: robot 0, alone and waiting, went on from its team's
    # State (it lost the rounds of the cut, so not exactly as well)
    cut_mean, clean_mean = (sum(final_losses(d).values()) / 3 for d in (cut_dir, clean_dir))
    assert cut_mean <= 1.5 * clean_mean, (final_losses(cut_dir), final_losses(clean_dir))
    assert "rounds behind its team, it goes on from" in learner0
