"""The world's drive when the robots explore (``explore.policy`` planned, uncertainty or frontier).

The drive goes in legs of ``explore.leg_s`` simulated seconds, tied to the learners' rounds so
that the same seed gives the same paths whatever the timing: leg 0 is one scan from each robot's
start; before leg L (L >= 1) the world waits for each driving robot's Goal of leg L, which its
learner chooses at training round L x ``explore.decide_every`` from what it learned of legs
0..L-1 (planned: its word that it reached that round); during the leg each robot follows its
goal's path (planned: its planned path, which it follows on if its learner's word does not come) at
``world.speed_mps``, scanning at ``world.lidar_rate_hz``; the robot's last scan of the leg has
``leg_end`` set, and its learner trains on legs 0..L from then on. A robot stops where its real
LiDAR shows a return on the path ahead (its map was wrong there: its learner re-plans at the
next leg) or where its body would touch a wall (counted as a bump; it never enters one). A robot's
drive ends (its last scan has ``last``) when it has driven ``explore.distance_m``, its policy has
nowhere left to go, its planned path is over, the learners have no round left for another leg,
or the team's coverage grew less than ``explore.stall_gain`` over ``explore.stall_legs`` legs.

``exploration.csv`` in the run directory gets one row per robot per scan (pose, distance driven,
the team's coverage of the reachable free space on the ground truth, the robot's latest val_bce
as heard: the one column that depends on timing).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.protocol import Goal, Metrics
from swarmmap.shared.world.explore import (
    GOAL_COLUMNS,
    Drive,
    RowLog,
    TeamCoverage,
    parse_starts,
    path_costs,
    path_to,
    spread_starts,
    stalled,
    start_cell,
)
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.paths import GridPlanner
from swarmmap.shared.world.sensing import beam_ends

log = logging.getLogger("world")
BODY_RADIUS_M = 0.1  # a TurtleBot3 Burger's footprint: the world never lets a robot's centre nearer a wall
MISSED_GOAL_WAIT_S = 2.0  # the wait for a robot whose last goal never came (a learner gone), until it sends one again


class Goals:
    """The Goals heard (robot, leg) -> Goal of legs 1..``legs``, for the drive to wait on."""

    def __init__(self, legs: int) -> None:
        self.legs = legs
        self.held: dict[tuple[int, int], Goal] = {}
        self.cond = threading.Condition()

    def add(self, msg: Goal) -> None:
        if msg.leg > self.legs:  # (no such leg: never kept)
            return
        with self.cond:
            self.held.setdefault((msg.sender, msg.leg), msg)  # (the first word of a leg counts)
            self.cond.notify_all()

    def wait(self, robots: dict[int, float], leg: int, stop: threading.Event) -> dict[int, Goal]:
        """The goals of ``leg`` of ``robots`` (robot -> seconds to wait for it) that came in time."""
        start = time.monotonic()
        with self.cond:
            while not stop.is_set():
                late = [r for r, wait in robots.items() if (r, leg) not in self.held and time.monotonic() - start < wait]
                if not late:
                    break
                self.cond.wait(0.2)
            return {r: self.held[(r, leg)] for r in robots if (r, leg) in self.held}


class LatestBce:
    """Each robot's newest val_bce as its Metrics came (exploration.csv's last column)."""

    def __init__(self) -> None:
        self.bce: dict[int, tuple[int, float]] = {}

    def add(self, msg: Metrics) -> None:
        if msg.round >= self.bce.get(msg.sender, (-1, 0.0))[0]:
            self.bce[msg.sender] = (msg.round, msg.val_bce)

    def of(self, robot: int) -> float | None:
        return self.bce[robot][1] if robot in self.bce else None


def explore_starts(cfg: RunConfig, grid: OccupancyGrid, planned: list[np.ndarray] | None) -> np.ndarray:
    """Where the robots start: ``explore.starts``, else their planned paths' starts (planned),
    else spread over the plan's free space by the seed; a ValueError naming a start in a wall."""
    if cfg.explore.starts:
        starts = np.array(parse_starts(cfg.explore.starts, cfg.robots), dtype=np.float64)
    elif planned is not None:
        return np.array([p[0] for p in planned], dtype=np.float64)
    else:
        return spread_starts(grid, cfg.robots, cfg.seed, clearance=max(cfg.explore.clearance_m, BODY_RADIUS_M + 0.1))
    rows, cols, inside = grid.cells(starts)
    clear = grid.clearance()
    for i, (r, c, ok) in enumerate(zip(rows, cols, inside)):
        if not ok or clear[r, c] < BODY_RADIUS_M:
            raise ValueError(f"explore.starts: robot {i}'s start ({starts[i][0]:g}, {starts[i][1]:g}) is "
                             f"{'outside the plan' if not ok else 'in or against a wall'}")
    return starts


def planned_from(starts: np.ndarray, paths: list[np.ndarray], grid: OccupancyGrid, clearance: float) -> list[np.ndarray]:
    """Each planned path with the way to it from the robot's start prepended (a start given apart from the plan)."""
    planner = GridPlanner(grid, clearance)
    out = []
    for start, path in zip(starts, paths):
        costs, pred = path_costs(planner, start)
        cell = start_cell(planner, path[0])
        if cell is None or not np.isfinite(costs[cell]):
            log.warning("no path from start (%.2f, %.2f) to its planned path: it drives straight", *start)
            out.append(np.vstack([start[None], path]))
        else:
            out.append(np.vstack([path_to(planner, start, pred, cell), path[1:]]))
    return out


def solid_truth(grid: OccupancyGrid, poses: np.ndarray, angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scans (N, B) that end at the ground truth's solid space as well as at the walls: a plan's
    outside is solid in its ground truth, but a beam through an exterior door would see it free
    (and a robot would choose goals there that it can never reach)."""
    step = grid.resolution / 2
    t = np.arange(step, float(ranges.max(initial=0.0)) + step, step)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (N, B, 2)
    pts = poses[:, None, None, :2] + t[None, None, :, None] * d[:, :, None, :]  # (N, B, T, 2)
    rows, cols, inside = grid.cells(pts)
    solid = ~inside | (grid.grid[np.clip(rows, 0, grid.grid.shape[0] - 1), np.clip(cols, 0, grid.grid.shape[1] - 1)] > 0)
    solid &= t[None, None, :] < ranges[..., None]
    first = np.where(solid.any(axis=-1), solid.argmax(axis=-1), 0)
    cut = solid.any(axis=-1) & (t[first] < ranges - 2 * grid.resolution)  # (not where it only rasterises a wall the beam hit)
    ranges, hit = ranges.copy(), hit.copy()
    ranges[cut] = t[first[cut]]
    hit[cut] = True
    return angles, ranges, hit


class Exploration:
    """The drive of :mod:`this module <swarmmap.services.world.exploring>` over a :class:`Simulation`;
    ``publish(i, pose, angles, ranges, hit, leg, leg_end, last)`` sends robot i's scan."""

    def __init__(self, cfg: RunConfig, sim, grid: OccupancyGrid, starts: np.ndarray, planned: list[np.ndarray] | None,
                 goals: Goals, bce: LatestBce, publish: Callable[..., None]):
        self.cfg, self.sim, self.goals, self.bce, self.publish = cfg, sim, goals, bce, publish
        w = cfg.world
        self.drives = [Drive(s.copy(), speed=w.speed_mps, clearance=BODY_RADIUS_M + 0.03, lookahead=0.6) for s in starts]
        if planned is not None:
            for d, path in zip(self.drives, planned):
                d.follow(path[1:])
        self.planned = planned is not None
        self.yaw = np.zeros(cfg.robots)
        self.clear = grid.clearance()
        self.grid = grid
        self.coverage = TeamCoverage(grid, starts)
        self.curve: list[float] = []  # the team's coverage at the end of each leg
        self.done = [False] * cfg.robots
        self.why: dict[int, str] = {}
        self.bumps = [0] * cfg.robots
        self.missed: set[int] = set()
        self.hits = [np.zeros((0, 2))] * cfg.robots
        self.legs = cfg.legs()  # the learners choose goals for legs 1..legs
        self.out = RowLog(cfg.run_dir / "exploration.csv") if cfg.run_dir is not None else None
        self.goal_log = RowLog(cfg.run_dir / "goals.csv", GOAL_COLUMNS) if cfg.run_dir is not None else None
        self.t = 0.0

    def run(self, stop: threading.Event) -> None:
        self.scan_all(leg=0, end=True)
        for leg in range(1, self.legs + 1):
            if stop.is_set() or all(self.done):
                break
            self.take_goals(leg, stop)  # (planned: the learners' word that they reached the leg's round)
            self.drive_leg(leg, stop)
        self.done = [True] * self.cfg.robots  # (stopped: every drive is over)
        for f in (self.out, self.goal_log):
            if f is not None:
                f.close()
        d = [f"{x.driven:.1f}" for x in self.drives]
        log.info("exploration (%s) over at %.1f s simulated: coverage %.1f%% of %d reachable free cells; driven %s m "
                 "(team %.1f m); %s", self.cfg.explore.policy, self.t, 100 * self.coverage.fraction(), self.coverage.total,
                 ", ".join(d), sum(x.driven for x in self.drives),
                 "; ".join(f"robot {i}: {why}" for i, why in sorted(self.why.items())) or "stopped")
        if any(self.bumps):
            log.warning("robots stopped against a wall (their path ran into one the LiDAR had not shown): %s",
                        ", ".join(f"robot {i} {n}x" for i, n in enumerate(self.bumps) if n))

    def take_goals(self, leg: int, stop: threading.Event) -> None:
        e = self.cfg.explore
        waits = {i: MISSED_GOAL_WAIT_S if i in self.missed else e.goal_wait_s for i in range(self.cfg.robots) if not self.done[i]}
        got = self.goals.wait(waits, leg, stop)
        for i in waits:
            goal = got.get(i)
            if goal is None:
                if i not in self.missed:
                    log.warning("robot %d: no goal for leg %d within %g s: it %s (this leg depends on timing)", i, leg,
                                waits[i], "drives on" if self.planned else "stays where it is")
                self.missed.add(i)
                if not self.planned:
                    self.drives[i].follow(np.zeros((0, 2)))
                continue
            self.missed.discard(i)
            if self.planned:  # (its path was planned before the run)
                continue
            if self.goal_log is not None:
                self.goal_log.row(i, leg, self.t, goal.x, goal.y, int(goal.done))
            if goal.done:
                self.end(i, f"nowhere left to go ({goal.reason or 'its policy says so'})")
                self.drives[i].follow(np.zeros((0, 2)))
            else:
                self.drives[i].follow(goal.path.numpy().astype(np.float64))

    def end(self, i: int, why: str) -> None:
        self.why.setdefault(i, why)

    def drive_leg(self, leg: int, stop: threading.Event) -> None:
        w, e = self.cfg.world, self.cfg.explore
        period = 1.0 / w.lidar_rate_hz
        scans = max(1, round(e.leg_s / period))
        sub = max(1, math.ceil(period / w.sim_step_s))
        for s in range(scans):
            if stop.is_set():
                return
            for _ in range(sub):
                self.step(period / sub)
            self.scan_all(leg, end=s == scans - 1)

    def step(self, dt: float) -> None:
        self.t += dt
        for i, d in enumerate(self.drives):
            if self.done[i] or i in self.why:
                continue
            before = d.pose.copy()
            left = self.cfg.explore.distance_m - d.driven
            d.speed = min(self.cfg.world.speed_mps, left / dt) if left > 0 else 0.0
            d.step(dt, self.hits[i])
            r, c, inside = self.grid.cells(d.pose)
            if not inside or self.clear[r, c] < BODY_RADIUS_M:  # its body would touch the wall: it stops short
                d.driven -= float(np.linalg.norm(d.pose - before))
                d.pose, d.blocked = before, True
                self.bumps[i] += 1
            if np.linalg.norm(d.pose - before) > 1e-9:
                self.yaw[i] = math.atan2(d.pose[1] - before[1], d.pose[0] - before[0])
            if d.driven >= self.cfg.explore.distance_m - 1e-9:
                self.end(i, f"distance budget of {self.cfg.explore.distance_m:g} m driven")
            elif self.planned and d.arrived:
                self.end(i, "its planned path is over")
        self.sim.place([d.pose for d in self.drives], self.yaw, self.t)

    def leg_over(self, leg: int) -> None:
        """Whose drive ends with this leg: the budget spent, nowhere to go, the last leg, a stalled team."""
        e = self.cfg.explore
        if leg >= self.legs and leg > 0:
            for i in range(self.cfg.robots):
                self.end(i, f"the learners' last leg ({leg}: rounds {self.cfg.learner.rounds}, a goal every "
                            f"{e.decide_every})")
        self.curve.append(self.coverage.fraction())
        if (why := stalled(self.curve, e.stall_legs, e.stall_gain)) is not None:
            for i in range(self.cfg.robots):
                self.end(i, why)

    def scan_all(self, leg: int, end: bool) -> None:
        """Every driving robot's scan; at a leg's ``end``, whose drive ends with it."""
        poses = self.sim.poses()
        angles, ranges, hit = solid_truth(self.grid, poses, *self.sim.scan(poses))
        for i in range(self.cfg.robots):
            if self.done[i]:
                continue
            self.coverage.add_scan(poses[i, :2], angles[i], ranges[i])
            self.hits[i] = beam_ends(poses[i], angles[i], ranges[i], hit[i])
        cov = self.coverage.fraction()
        if end:
            self.leg_over(leg)
        for i in range(self.cfg.robots):
            if self.done[i]:
                continue
            last = end and i in self.why
            self.publish(i, poses[i], angles[i], ranges[i], hit[i], leg, end, last)
            if self.out is not None:
                self.out.row(i, self.t, *map(float, self.drives[i].pose), self.drives[i].driven, cov, self.bce.of(i))
            self.done[i] = last
