"""The proof that the distributed learner is DiNNO: with the same seeds and data, the
multi-process Zenoh run and the in-process run (every node in one process, as in DiNNO's own
code) end with the same parameters and the same validation loss."""

from __future__ import annotations

import json
import subprocess

import pytest
import torch

from swarmmap.shared.learning.networks import load_model
from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e


def run(run_dir, *extra):
    proc = subprocess.run([*SWARMMAP, "up", "--preset", "smoke", "--robots", "3",
                           "--rounds", "12", "--seed", "5", "--run-dir", str(run_dir), *extra],
                          capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((run_dir / "summary.json").read_text())


THIN = ["--set", "learner.consensus=sigma", "--set", "learner.compression=quant", "--set", "learner.keyframe_every=3",
        "--set", "learner.exchange_every=3", "--set", "learner.unseen_weight=0.05"]  # coverage travels in the States


EXPLORE = ["--explore", "uncertainty", "--set", "explore.decide_every=3"]  # goals at rounds 3, 6 and 9, legs driven between


# The Bayesian network (sampled weights: the seeds must line up too); exploring (the robots drive where
# their maps' std says, in legs between the rounds: the same paths both ways); thin links with the
# fault trials, to keep the everyday tier short.
@pytest.mark.parametrize("links", [[], EXPLORE, pytest.param(THIN, marks=pytest.mark.faults)],
                         ids=["bnn", "bnn-explore", "bnn-sigma-quant-every-3"])
def test_zenoh_run_equals_inproc_run(tmp_path, links):
    extra = ["--set", "learner.model=bnn", "--set", "learner.model_shape=[2,64,32,32,1]", *links]
    zenoh = run(tmp_path / "zenoh", *extra)
    inproc = run(tmp_path / "inproc", "--transport", "inproc", *extra)
    assert zenoh["transport"] == "zenoh" and inproc["transport"] == "inproc"
    assert len({v["pid"] for v in zenoh["learners"].values()}) == 3
    assert len({v["pid"] for v in inproc["learners"].values()}) == 1
    for robot in "012":
        a = load_model(tmp_path / "zenoh" / "models" / f"robot-{robot}.pt").state_dict()
        b = load_model(tmp_path / "inproc" / "models" / f"robot-{robot}.pt").state_dict()
        for name in a:
            torch.testing.assert_close(a[name], b[name], rtol=0, atol=1e-6, msg=f"robot {robot} {name}")
        assert zenoh["learners"][robot]["final_val_bce"] == pytest.approx(inproc["learners"][robot]["final_val_bce"],
                                                                          abs=1e-6)
        # Both count the bytes of Algorithm 1's messages as encoded on the wire (resends may differ)
        sent = zenoh["learners"][robot]["bytes_sent"], inproc["learners"][robot]["bytes_sent"]
        assert 0.7 < sent[0] / sent[1] < 1.5, sent
    if links is EXPLORE:  # the same goals, the same driven paths (poses, distances, coverage), val_bce aside (as heard)
        assert zenoh["exploration"] == inproc["exploration"] and zenoh["exploration"]["team_distance_m"] > 1.0
        drives = [[line.rsplit(",", 1)[0] for line in (tmp_path / how / "exploration.csv").read_text().splitlines()]
                  for how in ("zenoh", "inproc")]
        assert drives[0] == drives[1]
        assert (tmp_path / "zenoh" / "goals.csv").read_text() == (tmp_path / "inproc" / "goals.csv").read_text()
