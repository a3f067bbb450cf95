"""LiDAR throughput and the world's real-time factor.

    python bench/lidar_rays.py [--floorplan F] [--robots 7] [--beams 360] [--scans 200]

Builds the world (default: the demo preset's procedural plan; any --floorplan works) with
N TurtleBot robots on their planned paths and prints:
- rays per second when every robot's beams go into one ``rayTestBatch`` and when each robot
  casts its own, over ``--scans`` scans of all robots at fixed poses;
- the real-time factor of the world's loop (robot motion, one scan per robot per LiDAR
  period, and encoding the Scan messages) over a whole traversal at the LDS-01's 5 Hz.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from swarmmap.services.world.simulation import Simulation, build_plan, robot_paths
from swarmmap.shared.run.config import resolve
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Scan, Tensor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--floorplan", default="procedural")
    ap.add_argument("--waypoints", default=None)
    ap.add_argument("--robots", type=int, default=7)
    ap.add_argument("--beams", type=int, default=360)
    ap.add_argument("--scans", type=int, default=200)
    args = ap.parse_args()
    cfg = resolve({"robots": args.robots, "world": {"floorplan": args.floorplan, "waypoints": args.waypoints,
                                                    "lidar_beams": args.beams, "lidar_rate_hz": 5.0}},
                  preset="demo", environ={})
    w = cfg.world
    plan = build_plan(cfg)
    grid = plan.occupancy(w.grid_resolution_m)
    paths = robot_paths(cfg, plan, grid)
    sim = Simulation(plan, paths, w)
    poses = sim.poses()
    angles = poses[:, 2:3] + sim.angles[None, :].astype(np.float64)
    rays = args.scans * angles.size
    print(f"plan {plan.name}: {args.robots} robots x {args.beams} beams, {args.scans} scans each")
    for batched in (True, False):
        t0 = time.perf_counter()
        for _ in range(args.scans):
            sim.cast(poses, angles, batched=batched)
        dt = time.perf_counter() - t0
        label = "one rayTestBatch for all robots" if batched else "one rayTestBatch per robot    "
        print(f"  {label}: {rays / dt:12,.0f} rays/s ({dt / args.scans * 1e3:.2f} ms per scan of all robots)")
    sim.close()

    sim = Simulation(plan, paths, w)
    period, next_scan, scans = 1.0 / w.lidar_rate_hz, 0.0, 0
    t0 = time.perf_counter()
    while not all(r.done for r in sim.robots):
        if sim.t + 1e-9 >= next_scan:
            poses = sim.poses()
            ang, ranges, hit = sim.scan(poses)
            for i in range(len(poses)):
                encode(Scan(run="bench", sender=i, seq=scans, t=sim.t, pose=poses[i].tolist(), max_range=w.lidar_max_range_m,
                            angles=Tensor.of(ang[i], "<f4"), ranges=Tensor.of(ranges[i], "<f4"), hit=Tensor.of(hit[i], "|u1")))
            scans += 1
            next_scan += period
        sim.step(w.sim_step_s)
    dt = time.perf_counter() - t0
    print(f"  world loop: {sim.t:.1f} s simulated ({scans} scans per robot at {w.lidar_rate_hz:g} Hz, "
          f"{w.speed_mps} m/s) in {dt:.2f} s: real-time factor {sim.t / dt:.1f}")
    sim.close()


if __name__ == "__main__":
    main()
