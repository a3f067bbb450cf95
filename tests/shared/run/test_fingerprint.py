"""The settings fingerprint: every config field is classified as counting or not, a setting that
changes results changes it, an operational one does not, and a plan file is known by its content."""

from __future__ import annotations

import pytest

from swarmmap.shared.run.config import resolve
from swarmmap.shared.run.fingerprint import COUNTED, NOT_COUNTED, config_fields, fingerprint_diff, settings_fingerprint


def test_every_config_field_is_classified_once():
    """A field added to the config must be put in COUNTED or NOT_COUNTED (shared/run/fingerprint.py):
    does it change what a run computes?"""
    fields = {f"{section}.{name}" for section, names in config_fields().items() for name in names}
    counted = {f"{section}.{name}" for section, names in COUNTED.items() for name in names}
    not_counted = {f"{section}.{name}" for section, names in NOT_COUNTED.items() for name in names}
    assert not (counted & not_counted), f"classified both ways: {sorted(counted & not_counted)}"
    assert not (fields - counted - not_counted), f"not classified: {sorted(fields - counted - not_counted)}"
    assert not ((counted | not_counted) - fields), f"no such field: {sorted((counted | not_counted) - fields)}"


def fingerprint(**cli) -> dict:
    return settings_fingerprint(resolve(cli, preset="smoke", environ={}))


@pytest.mark.parametrize("changed", [
    {"learner": {"lr_start": 0.02}}, {"learner": {"rho_init": 0.5}}, {"learner": {"rounds": 61}},
    {"learner": {"graph": "ring"}}, {"learner": {"compression": "f16"}}, {"learner": {"model_shape": [2, 64, 1]}},
    {"world": {"rooms_x": 3}}, {"world": {"lidar_beams": 90}}, {"lidar": {"samples_per_beam": 9}},
    {"faults": {"link_success": 0.9}}, {"seed": 1}, {"robots": 4},
])
def test_a_setting_that_changes_results_changes_the_fingerprint(changed):
    assert fingerprint(**changed) != fingerprint()


@pytest.mark.parametrize("changed", [
    {"learner": {"device": "cpu", "torch_threads": 2, "compute_slots": 1, "peer_timeout_s": 5, "checkpoint_every": 7}},
    {"log_level": "debug", "run_id": "other", "run_dir": "/tmp/elsewhere"}, {"observer": {"mc_samples": 3}},
    {"recorder": {"stall_timeout_s": 5}}, {"up": {"resume": True, "restarts": 0}}, {"zenoh": {"insecure": True}},
    {"world": {"time_scale": 2.0}},
])
def test_an_operational_setting_leaves_it_alone(changed):
    assert fingerprint(**changed) == fingerprint()


def test_the_differences_are_named_and_a_plan_file_is_known_by_its_content(tmp_path):
    mine, theirs = fingerprint(seed=7, learner={"lr_start": 0.02}), fingerprint()
    assert fingerprint_diff(theirs, mine) == "seed 0 there, 7 here, learner.lr_start 0.01 there, 0.02 here"
    assert fingerprint_diff(mine, mine) == ""
    assert "older swarmmap" in fingerprint_diff(None, mine)
    assert "checkpoint format 2" in fingerprint_diff({"checkpoint_format": 2, "seed": 0}, mine)
    plan = tmp_path / "plan.png"
    plan.write_bytes(b"one plan")
    before = fingerprint(world={"floorplan": str(plan)})
    plan.write_bytes(b"another plan at the same path")
    assert "world.floorplan_sha256" in fingerprint_diff(before, fingerprint(world={"floorplan": str(plan)}))
