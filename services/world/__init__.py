"""The world service (``swarmmap world``): a simulated world (:mod:`.simulation`, pybullet), a
world of real LiDAR logs (:mod:`.dataset`, ``world.dataset``) or ROS 2 robots heard live
(:mod:`.ros2live`, ``swarmmap ros2``), all behind the same Zenoh session (:mod:`.session`);
:mod:`.robot` is the robots' URDF.

This module imports neither: a log needs no pybullet world, and ``swarmmap world`` starts fast.
"""

from __future__ import annotations

import threading

from swarmmap.shared.run.config import RunConfig


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The world service's main loop, on real logs when ``world.dataset`` names some; the exit status."""
    if cfg.ros2.live:
        from swarmmap.services.world.ros2live import run as run_robots

        return run_robots(cfg, stop)
    if cfg.world.dataset:
        from swarmmap.services.world.dataset import run as run_logs

        return run_logs(cfg, stop)
    from swarmmap.services.world.simulation import run as run_simulation

    return run_simulation(cfg, stop)
