"""The settings a learner's checkpoint must share with the run that resumes from it.

A learner refuses to resume from a checkpoint written with another fingerprint (it names the
settings that differ); the launcher uses the same fingerprint to tell whether a run directory
holds another run.
"""

from __future__ import annotations

from swarmmap.shared.config import RunConfig

CHECKPOINT_FORMAT = 2


def settings_fingerprint(cfg: RunConfig) -> dict:
    """What a checkpoint must share with the run that resumes from it."""
    s = cfg.learner
    return {"checkpoint_format": CHECKPOINT_FORMAT, "seed": cfg.seed, "robots": cfg.robots, "model": s.model,
            "model_shape": list(s.model_shape), "algorithm": s.algorithm,
            "regularization": s.regularization if s.model == "bnn" else None, "data": s.data,
            "consensus": s.consensus, "exchange_every": s.exchange_every,
            "floorplan": cfg.world.floorplan, "waypoints": cfg.world.waypoints}
