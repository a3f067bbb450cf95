"""An experiment reuses a finished run with the same settings, also one made before a setting
was added (at its default, the new setting changes nothing it ran with)."""

from __future__ import annotations

import pytest
import yaml

from swarmmap.services.experiments.common import same_settings
from swarmmap.services.up.launcher import prepare
from swarmmap.shared.run.config import resolve


def write_run(run_dir, cfg, drop=()):
    run_dir.mkdir(parents=True)
    doc = prepare(cfg.model_copy(update={"run_dir": run_dir})).model_dump(mode="json")
    for field in drop:  # a run made before these learner settings existed
        doc["learner"].pop(field)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(doc))


@pytest.mark.integration
def test_a_run_made_before_a_setting_existed_is_the_same_run_at_its_default(tmp_path):
    cfg = resolve({"preset": "smoke", "seed": 3})
    write_run(tmp_path / "old", cfg, drop=("exchange_every_s", "lowrank_rank"))
    assert same_settings(tmp_path / "old", cfg)
    assert not same_settings(tmp_path / "old", resolve({"preset": "smoke", "seed": 3,
                                                        "learner": {"exchange_every_s": 5.0}}))
    assert not same_settings(tmp_path / "old", resolve({"preset": "smoke", "seed": 4}))
    write_run(tmp_path / "other", resolve({"preset": "smoke", "seed": 3, "learner": {"rho_init": 0.5}}))
    assert not same_settings(tmp_path / "other", cfg)
