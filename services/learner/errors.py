"""Why a learner stops: :class:`LearnerError` carries the exit status it asks for."""

from __future__ import annotations


class LearnerError(RuntimeError):
    """A learner cannot go on; ``status`` is the process exit status it asks for (2: a refusal
    that would only repeat, e.g. a checkpoint of other settings; 3: no data or no world; 4: no
    neighbour ready; 5: neighbours lost; 6: training diverged)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status
