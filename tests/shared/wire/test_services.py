"""The registry of a run's kinds of service and what is derived from it: identities, the access
policy's keys, up's order, the SLURM job's lines; compose.yaml checked against it."""

from __future__ import annotations

import yaml

from swarmmap.shared.wire.protocol import Keys
from swarmmap.shared.wire.services import Access, identities, kinds, policy_keys, slurm_lines, started_by_up
from tests.conftest import REPO


def test_swarmmaps_own_kinds_and_their_identities():
    assert list(kinds()) == ["router", "recorder", "observer", "world", "up", "status", "lidar", "learner"]
    assert identities(2) == ["router-0", "recorder-0", "observer-0", "world-0", "up-0", "status-0", "lidar-0", "lidar-1",
                             "learner-0", "learner-1"]
    assert identities(1, host_routers=True)[-1] == "router-r0"


def test_up_starts_the_recorder_first_and_the_world_last_and_slurm_the_same():
    assert [name for name, _ in started_by_up()] == ["recorder", "observer", "learner", "lidar", "world"]
    assert slurm_lines() == ["recorder one light ends-run", "observer one light", "learner per-robot compute",
                             "lidar per-robot light", "world one light"]


def test_each_identity_speaks_on_its_own_keys_and_reads_what_its_service_needs():
    keys = Keys("swarmmap", "r")
    speaks, reads = policy_keys(keys, Access(3, neighbours={0: {1}, 1: {0, 2}, 2: {1}}))
    assert speaks["lidar-1"] == sorted([keys.alive("lidar", 1), keys.samples(1)])
    assert reads["learner-0"] == sorted([keys.alive(), keys.run_done(), keys.samples(0), keys.world_map(), *keys.exchange(1),
                                         keys.scan(0), keys.scan(1), keys.goal(1)])  # (exploring: its team's scans and goals)
    assert keys.learner(0) in speaks["learner-0"] and keys.alive("explore", 0) in speaks["learner-0"]  # (its goal on its own keys)
    assert keys.goal("*") in reads["world-0"] and keys.goal("*") not in speaks["world-0"]
    assert keys.state("*") not in reads["status-0"] and keys.state("*") in reads["observer-0"]
    speaks, reads = policy_keys(keys, Access(3, inproc_learner=True))  # one learner process serves every robot
    assert keys.learner(2) in speaks["learner-0"] and speaks["learner-2"] == [keys.alive("learner", 2)]


def test_compose_runs_every_kind_up_starts_each_as_its_command_per_robot_ones_scaled():
    services = yaml.safe_load((REPO / "compose.yaml").read_text())["services"]
    every = kinds()
    for name, k in [("router", every["router"]), *started_by_up()]:
        assert name in services, f"compose.yaml has no {name} service"
        assert services[name]["command"][0] == name
        assert ("SWARMMAP_ROBOTS" in str(services[name].get("scale", ""))) == k.per_robot, name
    assert set(services) - {"start"} <= set(every), "a compose service that is no registered kind"
