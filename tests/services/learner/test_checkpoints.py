"""A learner's checkpoints and training points: refused when written with other settings (both
files), and a write that fails stops the learner naming the file and the disk."""

from __future__ import annotations

import numpy as np
import pytest

from swarmmap.services.learner.checkpoints import Checkpoints
from swarmmap.services.learner.errors import LearnerError
from swarmmap.shared.run.config import resolve
from swarmmap.shared.run.fingerprint import settings_fingerprint


def written(folder, **cli) -> Checkpoints:
    return Checkpoints(folder, 0, "r", settings_fingerprint(resolve(cli, preset="smoke", environ={})), online=False)


def save(ck: Checkpoints, k: int = 0) -> None:
    points, labels = np.zeros((4, 2), np.float32), np.ones(4, np.float32)
    ck.save(k, np.arange(3, dtype=np.float32), {"rho": 0.1}, {"bytes_sent": 10}, points, labels)


def test_a_checkpoint_and_its_training_points_resume_a_run_with_the_same_settings(tmp_path):
    save(written(tmp_path))
    again = written(tmp_path, learner={"device": "cpu", "peer_timeout_s": 3})  # operational settings may differ
    doc = again.resumable()
    points, labels = again.points(doc)
    assert doc["round"] == 0 and points.shape == (4, 2) and labels.sum() == 4


def test_a_checkpoint_or_training_points_of_other_settings_are_refused(tmp_path):
    save(written(tmp_path))
    other = written(tmp_path, lidar={"samples_per_beam": 9})
    with pytest.raises(LearnerError, match=r"refusing to resume from .*robot-0\.pt.*lidar\.samples_per_beam 8 there, 9 here"):
        other.resumable()
    save(other, k=5)  # a checkpoint of the other settings beside the first run's training points (kept: not round 0)
    with pytest.raises(LearnerError, match=r"robot-0-data\.pt: it was written by a run with other settings \(lidar\.samples_per_beam"):
        other.points(other.resumable())


@pytest.mark.integration
def test_a_checkpoint_that_cannot_be_written_stops_the_learner_naming_the_disk(tmpfs):
    full = tmpfs("64k")
    ck = Checkpoints(full / "checkpoints", 0, "r", settings_fingerprint(resolve(preset="smoke", environ={})), online=True)
    points, labels = np.zeros((20_000, 2), np.float32), np.ones(20_000, np.float32)  # 240 kB: more than the disk holds
    with pytest.raises(LearnerError) as info:
        ck.save(0, np.zeros(3, np.float32), {}, {}, points, labels)
    assert info.value.status == 1
    assert f"cannot write {full / 'checkpoints' / 'robot-0.pt'}: No space left on device (the disk of" in str(info.value)
    assert f"tmpfs mounted at {full}" in str(info.value)


def test_a_node_with_the_noise_contrastive_prior_resumes_from_its_checkpoint(tmp_path):
    """The quickstart's node (a BNN whose prior knows which cells its team covered): its checkpoint
    is read back by torch's safe loader, with the cells it heard of."""
    import torch

    from swarmmap.services.learner.registry import RuleChoice, make_node, node_inputs
    from swarmmap.shared.learning.networks import build_network

    cfg = resolve(preset="quickstart", environ={})
    bounds = (0.0, 0.0, 4.0, 4.0)
    points, labels = np.random.default_rng(0).uniform(0, 2, (64, 2)).astype(np.float32), np.zeros(64, np.float32)

    def node():
        inputs = node_inputs(cfg.learner, build_network(cfg.network(), bounds, 0), points, labels, 1, bounds)
        return make_node("dinno", inputs, RuleChoice.of(cfg.learner, {0: set()}, 0))

    first = node()
    first.coverage.others[-1, -1] = True  # a cell a teammate covered
    ck = Checkpoints(tmp_path, 0, "r", settings_fingerprint(cfg), online=True)
    ck.save(3, first.state(), first.checkpoint(), {}, points, labels)
    again = node()
    again.restore(ck.resumable()["node"])
    assert again.coverage.others[-1, -1] and torch.is_tensor(first.checkpoint()["coverage"])
