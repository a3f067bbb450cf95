"""``swarmmap ros2``: a team of ROS 2 robots, mapped live. It hears their scans on ROS 2, learns
while it hears, publishes their maps there and, exploring, sends each robot its next goal.

Run-book: ``swarmmap ros2 --namespaces robot_a robot_b [--extent xmin,ymin,xmax,ymax]
[--initial-poses "x,y,yaw;x,y,yaw"] [--explore uncertainty] [up's options]`` (needs rclpy:
``pip install 'swarmmap[ros2]'``, or a sourced ROS 2 install).

1. The world service is the robots themselves (:mod:`swarmmap.services.world.ros2live`): it
   subscribes to every namespace's ``/<ns>/scan`` (``sensor_msgs/LaserScan``) and ``/<ns>/odom``
   (``nav_msgs/Odometry``) and to ``/tf_static`` (the LiDAR's mount on the base), places each scan
   in the shared frame (``--initial-poses``: each robot's odometry origin there; it publishes
   ``map`` -> each odometry frame on ``/tf_static``, and warns when robots' odometry each began at
   their own origin), and sends the scans to the team as they come. The first ``ros2.warmup_s``
   seconds give the map's extent (``--extent``, which exploring robots need), the held-out
   validation set and the reference.
2. The learners learn while the scans come: online on a sliding window, or, exploring
   (``--explore uncertainty|frontier``), in legs of ``explore.leg_s`` seconds: at each leg a
   learner chooses its robot's goal from what the team learned so far and the world publishes it
   on ``/<ns>/goal_pose`` (``geometry_msgs/PoseStamped``, frame ``map``: Nav2's topic).
3. The observer (unless ``--no-observer``) publishes, at every evaluation, each robot's mean map on ``/<ns>/map``, its std on
   ``/<ns>/map_std`` (a model with one; ``100 x std / observer.std_max``) and the team's on ``/map``:
   ``nav_msgs/OccupancyGrid``, frame ``map``, reliable and transient local (a node that starts later
   gets the newest), at the saved maps' resolution (``observer.map_resolution_m``), in ROS's
   conventions (:mod:`swarmmap.shared.run.rosmaps`: 100 a confident wall, -1 where no beam went or
   the std says unknown).
4. When the team has finished, the bridge serves its final maps (the learners' saved ones) on the
   same topics until Ctrl-C (or for ``ros2.serve_s``). Everything heard is kept in
   ``RUN_DIR/input/<ns>/`` (a rosbag2, poses in the shared frame; also on Ctrl-C), replayable with
   ``swarmmap up --dataset``.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.rosmaps import GridPublisher, need_rclpy, ros_occupancy
from swarmmap.shared.run.rosout import grid_values, team_map

log = logging.getLogger("ros2")


def final_maps(cfg: RunConfig) -> tuple[tuple, dict[str, np.ndarray]] | None:
    """The team's final maps as the topics carry them, from the learners' saved maps and the cells
    the observer saw beams cross; None when a robot's map is missing."""
    maps_dir = cfg.run_dir / "maps"
    seen = None
    if (maps_dir / "ros2-seen.npz").exists():
        with np.load(maps_dir / "ros2-seen.npz") as f:
            seen = f["seen"]
    out: dict[str, np.ndarray] = {}
    means, stds = {}, {}
    info = None
    for i, ns in enumerate(cfg.ros2.namespaces):
        path = maps_dir / f"robot-{i}.npz"
        if not path.exists():
            log.warning("no final map of robot %s (%s): its maps are not served", ns, path)
            return None
        with np.load(path) as f:
            mean, std = f["mean"], f["std"] if "std" in f.files else None
            info = (float(f["resolution"]), tuple(float(v) for v in f["origin"]), mean.shape)
        out[f"/{ns}/map"] = ros_occupancy(mean, std, seen, cfg.ros2.unknown_std)
        if std is not None:
            out[f"/{ns}/map_std"] = grid_values(std, cfg.observer.std_max)
            stds[i] = std
        means[i] = mean
    out["/map"] = ros_occupancy(team_map(means), team_map(stds) if len(stds) == len(means) else None, seen,
                                cfg.ros2.unknown_std)
    return info, out


def serve(cfg: RunConfig, stop: threading.Event) -> int:
    """Serve the team's final maps until stopped (or ``ros2.serve_s``)."""
    got = final_maps(cfg)
    if got is None:
        return 1
    info, grids = got
    rclpy = need_rclpy()
    pub = GridPublisher(rclpy, "swarmmap_final_maps")
    try:
        for topic, data in grids.items():
            pub.publish(topic, info, data)
        how = f"for {cfg.ros2.serve_s:g} s (ros2.serve_s)" if cfg.ros2.serve_s else "until Ctrl-C"
        log.info("the team has finished; serving its final maps on %s %s", ", ".join(grids), how)
        deadline = time.monotonic() + cfg.ros2.serve_s if cfg.ros2.serve_s else None
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            stop.wait(0.5)
    finally:
        pub.close()
    return 0


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Map the robots live, then serve their final maps; the exit status."""
    from swarmmap.services import up as launcher

    s = cfg.ros2
    if not s.namespaces:
        raise ConfigError("config error:\n  ros2.namespaces: name the robots' namespaces, e.g. --namespaces robot_a robot_b")
    need_rclpy()
    learner = {"map_resolution_m": cfg.observer.map_resolution_m}  # the topics' cells are the saved maps'
    if not cfg.explore.active:
        learner["data"] = "online"  # it learns while it hears
    cfg = launcher.prepare(cfg.model_copy(update={
        "robots": len(s.namespaces), "ros2": s.model_copy(update={"publish": True, "live": True}),
        "learner": cfg.learner.model_copy(update=learner)}))
    if not cfg.up.observer:
        log.warning("no observer (--no-observer): no maps are published while the team learns, only its final maps "
                    "once it has finished")
    if (why := launcher.run_dir_problem(cfg)) is not None:
        raise ConfigError(f"config error:\n  run_dir: {why}")
    inputs = cfg.run_dir / "input"
    if inputs.exists() and any(inputs.iterdir()):
        raise ConfigError(f"config error:\n  run_dir: {inputs} holds the input of an earlier run, which is never overwritten; "
                          "choose another run directory (or replay it: swarmmap up --dataset " + f"{inputs}/*/*.mcap)")
    status = launcher.run(cfg, stop)
    if status != 0 or stop.is_set():
        return status
    return serve(cfg, stop)
