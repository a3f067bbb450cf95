"""A learner's checkpoints: what a round starts from, written so that a restarted learner resumes.

``RUN_DIR/checkpoints/robot-<i>.pt`` holds the round, the State, the node's own state (duals,
rho, optimizers, RNG states), the run id, the settings' fingerprint
(:func:`~swarmmap.shared.fingerprint.settings_fingerprint`) and the learner's counters. Offline,
the training points do not change: they are written once, beside it
(``robot-<i>-data.pt``), so that frequent checkpoints stay small. Every file is written
atomically; a checkpoint written with other settings is refused, never loaded.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from swarmmap.services.learner.errors import LearnerError
from swarmmap.shared.atomic import atomic_write_bytes


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
        mine, theirs = self.fingerprint, doc.get("fingerprint")
        if theirs != mine:
            what = ("it comes from an older swarmmap" if theirs is None else
                    ", ".join(f"{k} {theirs.get(k)!r} there, {v!r} here" for k, v in mine.items() if theirs.get(k) != v))
            raise LearnerError(f"robot {self.robot}: refusing to resume from {self.path}: it was written by a run "
                               f"with other settings ({what}). Run into another --run-dir, or remove "
                               f"{self.path.parent} to start this one afresh", 2)
        return doc

    def save(self, k: int, theta: np.ndarray, node: dict, counters: dict, points: np.ndarray, labels: np.ndarray) -> None:
        """Atomically write what round ``k`` starts from (and, the first time offline, the points)."""
        doc = {"round": k, "state": torch.from_numpy(theta.copy()), "node": node, "run_id": self.run_id,
               "fingerprint": self.fingerprint, "counters": counters}
        data = {"points": torch.from_numpy(points), "labels": torch.from_numpy(labels)}
        if self.online:
            doc |= data
        elif k == 0 or not self.data_path.exists():
            buf = io.BytesIO()
            torch.save(data | {"fingerprint": self.fingerprint}, buf)
            atomic_write_bytes(self.data_path, buf.getvalue())
        buf = io.BytesIO()
        torch.save(doc, buf)
        atomic_write_bytes(self.path, buf.getvalue())

    def points(self, doc: dict) -> tuple[np.ndarray, np.ndarray]:
        """The training points a checkpoint resumes with (in it, online; beside it, offline)."""
        if "points" not in doc:
            try:
                doc = torch.load(self.data_path, map_location="cpu", weights_only=True)
            except Exception as exc:
                raise LearnerError(f"robot {self.robot}: cannot read its training points {self.data_path}: {exc}", 2) from None
        return doc["points"].numpy(), doc["labels"].numpy()
