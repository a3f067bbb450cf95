"""``swarmmap up`` and ``swarmmap prepare``: a whole run started on this host and its run directory.

:mod:`.launcher` starts and watches the services (one process each) and ends the run;
:mod:`.preflight` checks what it can before anything starts; :mod:`.console` is up's progress
line and closing block; :mod:`.netns` puts each robot's host in a network namespace of its own
(``up --netns``, ``swarmmap net``); :mod:`.claim` is compose's start of a run. What other parts
of swarmmap use of it (the experiments, ``swarmmap ros2``) is named here.
"""

from __future__ import annotations

from swarmmap.services.up.launcher import Launcher, WayOut, prepare, run, run_dir_problem, write_config
from swarmmap.services.up.preflight import writable_problem

__all__ = ["Launcher", "WayOut", "prepare", "run", "run_dir_problem", "write_config", "writable_problem"]
