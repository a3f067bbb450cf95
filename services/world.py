"""The world simulator: a floor plan extruded into a pybullet world where robots drive their paths.

Run-book: ``swarmmap world --config RUN_DIR/config.yaml`` (``swarmmap up`` starts it last).
It builds the plan, its ground-truth grid and validation set, serves them on ``world/map``,
waits until every lidar streamer and learner of the run is alive, then drives the robots and
publishes one ``Scan`` per robot per LiDAR period on ``robots/<id>/scan`` (the robot's final
scan has ``last`` set). Afterwards it keeps serving the map until stopped.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
import pybullet
import trimesh

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig, WorldSettings
from swarmmap.shared.floorplan import FloorPlan, OccupancyGrid, path_length, plan_paths, point_along, procedural
from swarmmap.shared.protocol import Keys, Scan, Tensor, WorldMap, encode
from swarmmap.shared.sensing import beam_angles, validation_set

log = logging.getLogger("world")

ROBOT_RADIUS_M = 0.105  # TurtleBot3 Burger footprint
ROBOT_HEIGHT_M = 0.192


def build_plan(cfg: RunConfig) -> FloorPlan:
    """The run's floor plan (procedural, seeded by the run's seed)."""
    w = cfg.world
    return procedural(w.rooms_x, w.rooms_y, cfg.seed, room_min=w.room_min_m, room_max=w.room_max_m,
                      wall_thickness=w.wall_thickness_m, door_width=w.door_width_m,
                      extra_door_prob=w.extra_door_prob)


def plan_mesh(plan: FloorPlan, height: float) -> trimesh.Trimesh:
    """The walls extruded to ``height`` as one triangle mesh."""
    boxes = []
    for r in plan.walls:
        box = trimesh.creation.box(extents=(r.x1 - r.x0, r.y1 - r.y0, height))
        box.apply_translation(((r.x0 + r.x1) / 2, (r.y0 + r.y1) / 2, height / 2))
        boxes.append(box)
    return trimesh.util.concatenate(boxes)


@dataclass
class Robot:
    path: np.ndarray
    length: float
    s: float = 0.0
    done: bool = False


class Simulation:
    """A pybullet (DIRECT) world: the static plan mesh and kinematic robots on their paths."""

    def __init__(self, plan: FloorPlan, paths: list[np.ndarray], settings: WorldSettings):
        self.settings = settings
        self.client = pybullet.connect(pybullet.DIRECT)
        mesh = plan_mesh(plan, settings.wall_height_m)
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=mesh.vertices.tolist(), indices=mesh.faces.ravel().tolist(),
            flags=pybullet.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=self.client)
        self.plan_body = pybullet.createMultiBody(0, shape, physicsClientId=self.client)
        # Robots carry only a visual shape: the LiDAR sees the building, never another robot.
        visual = pybullet.createVisualShape(pybullet.GEOM_CYLINDER, radius=ROBOT_RADIUS_M, length=ROBOT_HEIGHT_M,
                                            physicsClientId=self.client)
        self.robots = [Robot(p, path_length(p)) for p in paths]
        self.bodies = [pybullet.createMultiBody(0, -1, visual, basePosition=[*p[0], ROBOT_HEIGHT_M / 2],
                                                physicsClientId=self.client) for p in paths]
        self.angles = beam_angles(settings.lidar_beams, settings.lidar_fov_deg)
        self.t = 0.0

    def poses(self) -> np.ndarray:
        """(N, 3) x, y, yaw of every robot."""
        out = []
        for r in self.robots:
            xy, yaw = point_along(r.path, r.s)
            out.append((xy[0], xy[1], yaw))
        return np.asarray(out)

    def step(self, dt: float) -> None:
        """Advance every robot ``dt`` seconds along its path."""
        self.t += dt
        for robot, body in zip(self.robots, self.bodies):
            robot.s = min(robot.length, robot.s + self.settings.speed_mps * dt)
            robot.done = robot.s >= robot.length
            xy, yaw = point_along(robot.path, robot.s)
            pybullet.resetBasePositionAndOrientation(
                body, [xy[0], xy[1], ROBOT_HEIGHT_M / 2], pybullet.getQuaternionFromEuler([0, 0, yaw]),
                physicsClientId=self.client)

    def scan(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast every robot's beams in one ``rayTestBatch``: absolute angles, ranges, hit (N, B)."""
        s = self.settings
        angles = poses[:, 2:3] + self.angles[None, :].astype(np.float64)
        dirs = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=-1)
        origin = np.concatenate([poses[:, :2], np.full((len(poses), 1), s.lidar_height_m)], axis=1)
        starts = np.repeat(origin[:, None, :], angles.shape[1], axis=1) + dirs * s.lidar_min_range_m
        ends = origin[:, None, :] + dirs * s.lidar_max_range_m
        starts, ends = starts.reshape(-1, 3), ends.reshape(-1, 3)
        fractions = []
        batch = pybullet.MAX_RAY_INTERSECTION_BATCH_SIZE
        for a in range(0, len(starts), batch):
            results = pybullet.rayTestBatch(starts[a : a + batch].tolist(), ends[a : a + batch].tolist(),
                                            physicsClientId=self.client)
            fractions.extend(r[2] if r[0] >= 0 else -1.0 for r in results)
        frac = np.asarray(fractions).reshape(angles.shape)
        hit = frac >= 0
        span = s.lidar_max_range_m - s.lidar_min_range_m
        ranges = np.where(hit, s.lidar_min_range_m + frac * span, s.lidar_max_range_m)
        return angles, ranges, hit

    def close(self) -> None:
        pybullet.disconnect(self.client)


def world_map_message(cfg: RunConfig, grid: OccupancyGrid) -> WorldMap:
    """The ground truth and validation set that the world serves on ``world/map``."""
    w = cfg.world
    pts, labels = validation_set(grid, w.val_scans, w.val_beams, w.lidar_max_range_m,
                                 cfg.lidar.samples_per_beam, cfg.seed, cfg.lidar.occupied_depth_m)
    return WorldMap(run=cfg.run_id, sender=0, resolution=grid.resolution, origin=list(grid.origin),
                    grid=Tensor.of(grid.grid, "|u1"), val_points=Tensor.of(pts, "<f4"),
                    val_labels=Tensor.of(labels, "<f4"), robots=cfg.robots)


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The world service's main loop; returns the process exit status."""
    w = cfg.world
    plan = build_plan(cfg)
    grid = plan.occupancy(w.grid_resolution_m)
    paths = plan_paths(plan, cfg.robots, cfg.seed, w.rooms_per_robot)
    map_payload = encode(world_map_message(cfg, grid))
    sim = Simulation(plan, paths, w)
    log.info("plan %s: %d rooms, %d doors, %.1f x %.1f m; paths %s m", plan.name, len(plan.rooms), len(plan.doors),
             plan.bounds[2] - plan.bounds[0], plan.bounds[3] - plan.bounds[1],
             ", ".join(f"{r.length:.1f}" for r in sim.robots))
    keys = Keys(cfg.key_prefix, cfg.run_id)
    with Bus.open(cfg.zenoh, keys, "world", 0) as bus:
        bus.serve(keys.world_map(), lambda: map_payload)
        pubs = [bus.publisher(keys.scan(i)) for i in range(cfg.robots)]
        bus.announce()
        wanted = {str(i) for i in range(cfg.robots)}
        for service in ("lidar", "learner"):
            missing = bus.wait_alive(service, wanted, w.wait_for_consumers_s, stop)
            if stop.is_set():
                return 0
            if missing:
                log.warning("driving without %s %s (not alive after %.0f s)", service, sorted(missing), w.wait_for_consumers_s)
        period = 1.0 / w.lidar_rate_hz
        next_scan = 0.0
        seq = 0
        start = time.monotonic()
        finished = [False] * cfg.robots
        while not stop.is_set() and not all(finished):
            if sim.t + 1e-9 >= next_scan:
                poses = sim.poses()
                angles, ranges, hit = sim.scan(poses)
                for i, pub in enumerate(pubs):
                    if finished[i]:
                        continue
                    last = sim.robots[i].done
                    pub.put(Scan(run=cfg.run_id, sender=i, seq=seq, t=sim.t, pose=poses[i].tolist(),
                                 max_range=w.lidar_max_range_m, angles=Tensor.of(angles[i], "<f4"),
                                 ranges=Tensor.of(ranges[i], "<f4"), hit=Tensor.of(hit[i], "|u1"), last=last))
                    finished[i] = last
                seq += 1
                next_scan += period
            sim.step(w.sim_step_s)
            if w.time_scale > 0:
                ahead = sim.t / w.time_scale - (time.monotonic() - start)
                if ahead > 0:
                    stop.wait(ahead)
        elapsed = time.monotonic() - start
        log.info("traversal done: %d scans per robot, %.1f s simulated in %.1f s (real-time factor %.1f)",
                 seq, sim.t, elapsed, sim.t / max(elapsed, 1e-9))
        sim.close()
        stop.wait()  # keep serving the map until told to stop
    return 0
