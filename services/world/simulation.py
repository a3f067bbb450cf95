"""The world simulator: a floor plan extruded into a pybullet world where robots drive their paths.

Run-book: ``swarmmap world --config RUN_DIR/config.yaml`` (``swarmmap up`` starts it last).
It builds the plan (``world.floorplan``: procedural, a CubiCasa5K SVG or a DiNNO PNG), its
ground-truth grid and validation set, serves them on ``world/map``,
waits until the services of ``world.wait_for`` are alive (every lidar streamer and learner,
the recorder, and the observer when one records the run), then drives the robots and
publishes one ``Scan`` per robot per LiDAR period on ``robots/<id>/scan`` (the robot's final
scan has ``last`` set). Afterwards it keeps serving the map until the run is over
(``run/done``) or it is stopped.
``swarmmap world --floorplan F --export DIR`` writes DIR/plan.stl, occupancy.png and
occupancy.npz and exits.
"""

from __future__ import annotations

import functools
import io
import logging
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet
import shapely
from scipy import ndimage

from swarmmap.services.world.exploring import Exploration, Goals, LatestBce, explore_starts, planned_from
from swarmmap.services.world.robot import LIDAR_LINK, write_urdf
from swarmmap.services.world.session import serving
from swarmmap.shared.run.atomic import atomic_write_bytes, save_png
from swarmmap.shared.run.config import RunConfig, WorldSettings
from swarmmap.shared.run.mapfiles import save_ros_map, trinary_pixels
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Goal, Metrics, Scan, Tensor, WorldMap
from swarmmap.shared.world.floorplan import FloorPlan, OccupancyGrid, PlanError
from swarmmap.shared.world.paths import coverage, path_length, point_along
from swarmmap.shared.world.plans import load_floorplan, robot_paths
from swarmmap.shared.world.sensing import beam_angles, validation_recipe, validation_set

log = logging.getLogger("world")

WALLS_GROUP = 1
ROBOTS_GROUP = 4


def build_plan(cfg: RunConfig) -> FloorPlan:
    """The run's floor plan (``world.floorplan``; procedural plans are seeded by the run's seed)."""
    return load_floorplan(cfg.world.floorplan, cfg.world, cfg.seed)


def export(cfg: RunConfig, plan: FloorPlan, grid: OccupancyGrid, folder: Path) -> None:
    """``plan.stl`` (the extruded walls), ``occupancy.png`` and ``occupancy.npz`` (grid, resolution, origin)."""
    mesh = plan.mesh(cfg.world.wall_height_m)
    atomic_write_bytes(folder / "plan.stl", mesh.export(file_type="stl"))
    save_png(folder / "occupancy.png", grid.grid.astype(float))
    buf = io.BytesIO()
    np.savez_compressed(buf, grid=grid.grid, resolution=grid.resolution, origin=np.asarray(grid.origin))
    atomic_write_bytes(folder / "occupancy.npz", buf.getvalue())
    write_ros_map(plan, grid, folder)
    log.info("exported %s: plan.stl (%d triangles, watertight %s), occupancy %s at %.3f m, ROS map map.yaml + map.pgm",
             folder, len(mesh.faces), mesh.is_watertight, grid.grid.shape, grid.resolution)


def write_ros_map(plan: FloorPlan, grid: OccupancyGrid, folder: Path) -> None:
    """The ground truth as a ROS ``map_server`` map (``map.yaml`` + ``map.pgm``, trinary, as
    map_saver writes them: 254 free, 0 occupied, 205 unknown). Unknown: the grid's own unknown
    cells and, for a plan with wall outlines, the occupied cells outside every wall (the space
    around the building, which no robot could map)."""
    unknown = grid.unknown.copy() if grid.unknown is not None else np.zeros(grid.grid.shape, bool)
    if plan.raster is None:
        pts, shape = grid.centres()
        wall = shapely.contains_xy(plan.walls, pts[:, 0], pts[:, 1]).reshape(shape)
        unknown |= (grid.grid > 0) & ~ndimage.binary_dilation(wall, iterations=1)
    save_ros_map(folder / "map.yaml", trinary_pixels(grid.grid > 0, unknown), grid.resolution, grid.origin)


@dataclass
class Robot:
    path: np.ndarray
    length: float
    s: float = 0.0
    done: bool = False


class Simulation:
    """A pybullet (DIRECT) world: the plan's walls as one static mesh and URDF robots that follow
    their paths kinematically; the LiDAR casts from each robot's ``base_scan`` link."""

    def __init__(self, plan: FloorPlan, paths: list[np.ndarray], settings: WorldSettings):
        self.settings = settings
        self.client = pybullet.connect(pybullet.DIRECT)
        mesh = plan.mesh(settings.wall_height_m)
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=mesh.vertices.tolist(), indices=mesh.faces.ravel().tolist(),
            flags=pybullet.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=self.client)
        self.plan_body = pybullet.createMultiBody(0, shape, physicsClientId=self.client)
        # Explicit groups: Bullet puts static bodies in a group of its own choosing.
        pybullet.setCollisionFilterGroupMask(self.plan_body, -1, WALLS_GROUP, WALLS_GROUP, physicsClientId=self.client)
        with tempfile.TemporaryDirectory() as tmp:
            urdf = str(write_urdf(Path(tmp)))
            self.robots = [Robot(p, path_length(p)) for p in paths]
            self.bodies = [pybullet.loadURDF(urdf, [*p[0], 0.0], useFixedBase=True, physicsClientId=self.client)
                           for p in paths]
        names = [pybullet.getJointInfo(self.bodies[0], j, physicsClientId=self.client)[12].decode()
                 for j in range(pybullet.getNumJoints(self.bodies[0], physicsClientId=self.client))]
        self.lidar_link = names.index(LIDAR_LINK)
        for body in self.bodies:  # the LiDAR sees the building, never a robot
            for link in range(-1, len(names)):
                pybullet.setCollisionFilterGroupMask(body, link, ROBOTS_GROUP, 0, physicsClientId=self.client)
        self.angles = beam_angles(settings.lidar_beams, settings.lidar_fov_deg)
        self.t = 0.0
        self.step(0.0)

    def poses(self) -> np.ndarray:
        """(N, 3) x, y, yaw of every robot's LiDAR."""
        out = []
        for body in self.bodies:
            pos, orn = pybullet.getLinkState(body, self.lidar_link, computeForwardKinematics=True,
                                             physicsClientId=self.client)[4:6]
            yaw = pybullet.getEulerFromQuaternion(orn)[2]
            out.append((pos[0], pos[1], yaw))
        return np.asarray(out)

    def step(self, dt: float) -> None:
        """Advance every robot ``dt`` seconds along its path, heading along the path."""
        self.t += dt
        for robot, body in zip(self.robots, self.bodies):
            robot.s = min(robot.length, robot.s + self.settings.speed_mps * dt)
            robot.done = robot.s >= robot.length
            xy, yaw = point_along(robot.path, robot.s)
            pybullet.resetBasePositionAndOrientation(body, [xy[0], xy[1], 0.0], pybullet.getQuaternionFromEuler([0, 0, yaw]),
                                                     physicsClientId=self.client)

    def place(self, positions: list[np.ndarray], yaws: np.ndarray, t: float) -> None:
        """Put every robot at ``positions`` (x, y) heading ``yaws`` at simulated time ``t`` (exploration drives them)."""
        self.t = t
        for xy, yaw, body in zip(positions, yaws, self.bodies):
            pybullet.resetBasePositionAndOrientation(body, [xy[0], xy[1], 0.0], pybullet.getQuaternionFromEuler([0, 0, yaw]),
                                                     physicsClientId=self.client)

    def cast(self, poses: np.ndarray, angles: np.ndarray, batched: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Ranges and hit flags (N, B) of beams along absolute ``angles`` (N, B) from ``poses``;
        all robots' rays in one ``rayTestBatch`` (``batched``) or one call per robot (default:
        ``world.ray_batch``)."""
        s = self.settings
        batched = s.ray_batch == "all" if batched is None else batched
        dirs = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=-1)
        origin = np.concatenate([poses[:, :2], np.full((len(poses), 1), s.lidar_height_m)], axis=1)
        starts = origin[:, None, :] + dirs * s.lidar_min_range_m
        ends = origin[:, None, :] + dirs * s.lidar_max_range_m
        groups = [slice(None)] if batched else [slice(i, i + 1) for i in range(len(poses))]
        frac = np.empty(angles.shape)
        for g in groups:
            a, b = starts[g].reshape(-1, 3), ends[g].reshape(-1, 3)
            out = []
            for k in range(0, len(a), pybullet.MAX_RAY_INTERSECTION_BATCH_SIZE):
                chunk = slice(k, k + pybullet.MAX_RAY_INTERSECTION_BATCH_SIZE)
                results = pybullet.rayTestBatch(a[chunk].tolist(), b[chunk].tolist(), collisionFilterMask=WALLS_GROUP, numThreads=0,
                                                physicsClientId=self.client)
                out.extend(r[2] if r[0] >= 0 else -1.0 for r in results)
            frac[g] = np.asarray(out).reshape(frac[g].shape)
        hit = frac >= 0
        span = s.lidar_max_range_m - s.lidar_min_range_m
        return np.where(hit, s.lidar_min_range_m + frac * span, s.lidar_max_range_m), hit

    def scan(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every robot's scan: absolute beam angles, ranges, hit (N, B)."""
        angles = poses[:, 2:3] + self.angles[None, :].astype(np.float64)
        ranges, hit = self.cast(poses, angles)
        return angles, ranges, hit

    def close(self) -> None:
        pybullet.disconnect(self.client)


def wire_grid(grid: OccupancyGrid) -> np.ndarray:
    """The grid as WorldMap carries it: 0 free, 1 occupied, 2 unknown (a ROS map's)."""
    out = grid.grid.astype(np.uint8)
    if grid.unknown is not None:
        out = np.where(grid.unknown, np.uint8(2), out)
    return out


def world_map_message(cfg: RunConfig, grid: OccupancyGrid, paths: list[np.ndarray] | None = None,
                      points: bool = True) -> WorldMap:
    """The ground truth, validation set and final robot positions that the world serves on
    ``world/map``: the validation set as points, or (``points`` false) as the recipe to draw
    them from the grid."""
    w, beams = cfg.world, cfg.labelling()  # labelled as the streamers label training points (DiNNO)
    args = (grid, w.val_scans, w.val_beams, w.lidar_max_range_m, beams.samples_per_beam, cfg.seed, beams.occupied_depth_m)
    if points:
        pts, labels = validation_set(*args)
        val = {"val_points": Tensor.of(pts, "<f4"), "val_labels": Tensor.of(labels, "<f4")}
    else:
        val = {"validation": validation_recipe(*args)}
    return WorldMap(run=cfg.run_id, sender=0, resolution=grid.resolution, origin=list(grid.origin),
                    grid=Tensor.of(wire_grid(grid), "|u1"), robots=cfg.robots, **val,
                    positions=None if paths is None else Tensor.of(np.array([p[-1] for p in paths]), "<f4"))


def map_replies(cfg: RunConfig, grid: OccupancyGrid, paths: list[np.ndarray] | None) -> Callable[[str], bytes]:
    """The world's answer to a query on ``world/map`` with these parameters: the validation set
    as its recipe, or its points when the parameters ask for ``points`` (encoded once, when first
    asked for)."""
    recipe = encode(world_map_message(cfg, grid, paths, points=False))
    with_points = functools.cache(lambda: encode(world_map_message(cfg, grid, paths)))
    return lambda parameters: (with_points() if any(p.partition("=")[0] == "points" for p in parameters.split(";"))
                               else recipe)


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The simulated world's main loop; returns the process exit status."""
    w = cfg.world
    try:
        plan = build_plan(cfg)
        grid = plan.occupancy(w.grid_resolution_m)
        if w.export is not None:
            export(cfg, plan, grid, w.export)
            return 0
        if cfg.explore.active:
            return explore(cfg, plan, grid, stop)
        paths = robot_paths(cfg, plan, grid)
    except PlanError as exc:
        log.error("floor plan refused: %s", exc)
        return 2
    map_reply = map_replies(cfg, grid, paths)
    sim = Simulation(plan, paths, w)
    x0, y0, x1, y1 = plan.bounds
    log.info("rooms: %s", ", ".join(f"{i} {name}" for i, name in enumerate(plan.room_names)))
    log.info("doors: %s", ", ".join(f"{i} at ({d.centroid.x:.1f}, {d.centroid.y:.1f})" for i, d in enumerate(plan.doors)) or "none")
    if plan.closed:
        log.info("doors closed: %s (the rooms behind them stay unseen)", plan.closed)
    log.info("plan %s (%s): %d rooms, %d doors, %.1f x %.1f m; paths %s m; free space within LiDAR range of a path: "
             "%s (team %.0f%%)", plan.name, plan.kind, len(plan.rooms), len(plan.doors), x1 - x0, y1 - y0,
             ", ".join(f"{r.length:.1f}" for r in sim.robots),
             ", ".join(f"{100 * coverage([p], grid, w.lidar_max_range_m):.0f}%" for p in paths),
             100 * coverage(paths, grid, w.lidar_max_range_m))
    try:
        with serving(cfg, map_reply, stop) as pubs:
            if pubs is None:
                return 0
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
            stop.wait()  # keep serving the map until told to stop
    finally:
        sim.close()
    return 0


def explore(cfg: RunConfig, plan: FloorPlan, grid: OccupancyGrid, stop: threading.Event) -> int:
    """The world of an exploring team (:mod:`~swarmmap.services.world.exploring`): the robots start
    where ``explore.starts`` puts them (or spread by the seed, or at their planned paths' starts)
    and drive in legs towards the goals their learners choose."""
    w, e = cfg.world, cfg.explore
    if cfg.run_dir is not None and (drove := cfg.run_dir / "exploration.csv").exists() and drove.read_text().count("\n") > 1:
        log.error("%s holds the drive of this run's robots: a world started again cannot take up a drive it lost (the "
                  "robots' positions, goals and what they saw are not checkpointed)", drove)
        return 2
    planned = robot_paths(cfg, plan, grid) if e.policy == "planned" else None
    try:
        starts = explore_starts(cfg, grid, planned)
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    if planned is not None and e.starts:
        planned = planned_from(starts, planned, grid, w.robot_clearance_m)
    still = [s[None] for s in starts]
    sim = Simulation(plan, still, w)
    log.info("exploring %s (%s) by %s: %d robots from %s; legs of %.0f s, a goal every %d rounds, %.0f m each at most",
             plan.name, plan.kind, e.policy, cfg.robots, "; ".join(f"({x:.2f}, {y:.2f})" for x, y in starts), e.leg_s,
             e.decide_every, e.distance_m)
    goals, bce = Goals(cfg.legs()), LatestBce()

    def listen(bus) -> None:
        bus.subscribe(bus.keys.goal("*"), Goal, goals.add)
        bus.subscribe(bus.keys.metrics("*"), Metrics, bce.add)

    try:
        with serving(cfg, map_replies(cfg, grid, still), stop, listen) as pubs:
            if pubs is None:
                return 0
            seqs = [0] * cfg.robots

            def publish(i, pose, angles, ranges, hit, leg, leg_end, last) -> None:
                pubs[i].put(Scan(run=cfg.run_id, sender=i, seq=seqs[i], t=sim.t, pose=pose.tolist(),
                                 max_range=w.lidar_max_range_m, angles=Tensor.of(angles, "<f4"),
                                 ranges=Tensor.of(ranges, "<f4"), hit=Tensor.of(hit, "|u1"), last=last, leg=leg,
                                 leg_end=leg_end))
                seqs[i] += 1

            start = time.monotonic()
            Exploration(cfg, sim, grid, starts, planned, goals, bce, publish).run(stop)
            log.info("drive done: %s scans per robot, %.1f s simulated in %.1f s", seqs, sim.t, time.monotonic() - start)
            stop.wait()
    finally:
        sim.close()
    return 0
