"""A learner's checkpoints: what a round starts from, written so that a restarted learner resumes.

``RUN_DIR/checkpoints/robot-<i>.pt`` holds the round, the State, the node's own state (duals,
rho, optimizers, RNG states), the run id, the settings' fingerprint
(:func:`~swarmmap.shared.run.fingerprint.settings_fingerprint`) and the learner's counters. Offline,
the training points do not change: they are written once, beside it
(``robot-<i>-data.pt``, with the fingerprint too), so that frequent checkpoints stay small.
Every file is written atomically; a checkpoint or a training-points file written with other
settings is refused, never loaded, and one that cannot be written (a full disk) stops the learner
with a message naming the file and the disk.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from swarmmap.services.learner.errors import LearnerError
from swarmmap.shared.run.atomic import atomic_write_bytes
from swarmmap.shared.run.disk import disk_words
from swarmmap.shared.run.fingerprint import fingerprint_diff


class Checkpoints:
    """Robot ``robot``'s checkpoint in ``folder`` (``RUN_DIR/checkpoints``)."""

    def __init__(self, folder: Path, robot: int, run_id: str, fingerprint: dict, online: bool):
        self.path = folder / f"robot-{robot}.pt"
        self.data_path = folder / f"robot-{robot}-data.pt"
        self.robot, self.run_id, self.fingerprint, self.online = robot, run_id, fingerprint, online

    def resumable(self) -> dict | None:
        """The checkpoint, if there is one; one written with other settings is refused (LearnerError)."""
        for stale in self.path.parent.glob(f".robot-{self.robot}*.tmp"):
            stale.unlink(missing_ok=True)  # left by a learner killed while writing: the checkpoint itself is whole
        if not self.path.exists():
            return None
        try:
            doc = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a checkpoint we cannot read is not silently ignored
            raise LearnerError(f"robot {self.robot}: cannot read checkpoint {self.path}: {exc}", 2) from None
        self.refuse_other(self.path, doc.get("fingerprint"))
        return doc

    def refuse_other(self, path: Path, theirs: dict | None) -> None:
        """Raise LearnerError (status 2) when ``path`` was written with another fingerprint."""
        if theirs != self.fingerprint:
            raise LearnerError(f"robot {self.robot}: refusing to resume from {path}: it was written by a run "
                               f"with other settings ({fingerprint_diff(theirs, self.fingerprint)}). Run into another "
                               f"--run-dir, or remove {self.path.parent} to start this one afresh", 2)

    def save(self, k: int, theta: np.ndarray, node: dict, counters: dict, points: np.ndarray, labels: np.ndarray) -> None:
        """Atomically write what round ``k`` starts from (and, the first time offline, the points)."""
        doc = {"round": k, "state": torch.from_numpy(theta.copy()), "node": node, "run_id": self.run_id,
               "fingerprint": self.fingerprint, "counters": counters}
        data = {"points": torch.from_numpy(points), "labels": torch.from_numpy(labels)}
        if self.online:
            doc |= data
        elif k == 0 or not self.data_path.exists():
            self.write(self.data_path, data | {"fingerprint": self.fingerprint})
        self.write(self.path, doc)

    def write(self, path: Path, doc: dict) -> None:
        """``doc`` into ``path``, atomically; a write that fails stops the learner (status 1) naming the disk."""
        buf = io.BytesIO()
        torch.save(doc, buf)
        try:
            atomic_write_bytes(path, buf.getvalue())
        except OSError as exc:
            raise LearnerError(f"robot {self.robot}: cannot write {path}: {exc.strerror or exc} ({disk_words(path.parent)})", 1) from None

    def points(self, doc: dict) -> tuple[np.ndarray, np.ndarray]:
        """The training points a checkpoint resumes with (in it, online; beside it, offline)."""
        if "points" not in doc:
            try:
                doc = torch.load(self.data_path, map_location="cpu", weights_only=True)
            except Exception as exc:
                raise LearnerError(f"robot {self.robot}: cannot read its training points {self.data_path}: {exc}", 2) from None
            self.refuse_other(self.data_path, doc.get("fingerprint"))
        return doc["points"].numpy(), doc["labels"].numpy()
