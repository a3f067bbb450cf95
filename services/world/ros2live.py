"""The world of a team of ROS 2 robots (``swarmmap ros2``, ``ros2.live``): the robots themselves,
heard live (:mod:`.rosrobots`), in place of a simulation.

1. **Warm-up**: the first ``ros2.warmup_s`` seconds of every robot's scans (at least
   ``world.dataset_holdout_every`` of them) give the map (``ros2.extent``, else what they saw plus
   ``world.dataset_margin_m``), the held-out validation set (every ``dataset_holdout_every``-th
   warm-up scan, never trained on) and the reference (the log-odds grid of the others), served on
   ``world/map``. A robot that sent no scan with odometry within ``ros2.wait_s`` is refused by name.
2. Once the team is alive, every scan is sent on ``robots/<i>/scan`` as it comes (a robot's newest
   one is held back until the next, so that the last of a leg or of the input can be marked).
   **Not exploring**, the learners learn online meanwhile, and the input is over once no robot sent
   a scan for ``ros2.idle_s`` (or after ``ros2.max_input_s``). **Exploring**, leg 0 is what came
   before the team started; for leg L (L >= 1) the world waits for each driving robot's Goal,
   publishes it on ``/<ns>/goal_pose`` and sends what comes for ``explore.leg_s`` seconds as leg L.
   A robot's drive ends on its distance budget (``explore.distance_m``, measured on its poses), when
   its learner has nowhere left to go, on the learners' last leg or when the team's coverage
   stalled; it is then sent its current pose as its goal (stay).
3. Exploring, ``exploration.csv`` and ``goals.csv`` as a simulated world writes them, with
   ``sim_time_s`` the seconds since the robots' first scan and ``coverage`` the share of the map's
   extent that any beam crossed (there is no ground truth).
4. On exit (the run over, Ctrl-C, a failure) what was heard is written to ``RUN_DIR/input/<ns>/``.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np

from swarmmap.services.world.dataset import describe, world_map_message
from swarmmap.services.world.exploring import Goals, LatestBce
from swarmmap.services.world.rosrobots import RosRobots, join, refuse_silent
from swarmmap.services.world.session import serving
from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.sections import parse_extent
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Goal, Metrics, Scan, Tensor
from swarmmap.shared.world.datasets import DatasetError, LaserLog
from swarmmap.shared.world.explore import GOAL_COLUMNS, RowLog, TeamCoverage, stalled
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.teams import Team, make_team

log = logging.getLogger("world")
POLL_S = 0.05


def warm_up(cfg: RunConfig, robots: RosRobots, stop: threading.Event) -> list[LaserLog] | None:
    """Every robot's warm-up scans (see the module); None when told to stop meanwhile."""
    s, n = cfg.ros2, len(robots.names)
    need = cfg.world.dataset_holdout_every
    parts: list[list[LaserLog]] = [[] for _ in range(n)]
    first: dict[int, float] = {}
    start = said = time.monotonic()
    while not stop.is_set():
        now = time.monotonic()
        for i in range(n):
            if (got := robots.take(i)) is not None:
                parts[i].append(got)
                first.setdefault(i, now)
        counts = [sum(len(p) for p in parts[i]) for i in range(n)]
        if all(i in first and now - first[i] >= s.warmup_s and counts[i] >= need for i in range(n)):
            break
        if now - start > s.wait_s:
            raise refuse_silent(robots, [i for i in range(n) if i not in first], s.wait_s) if len(first) < n else \
                ConfigError(f"ros2: fewer than {need} scans (world.dataset_holdout_every) from "
                            f"{', '.join(robots.names[i] for i in range(n) if counts[i] < need)} within {s.wait_s:.0f} s")
        if now - said >= 10:
            said = now
            log.info("warm-up: heard %s", ", ".join(f"{ns} {c} scans" for ns, c in zip(robots.names, counts)))
        stop.wait(POLL_S)
    else:
        return None
    if n > 1 and s.initial_poses == "" and len(own := robots.own_origins()) > 1:
        log.warning("robots %s each began their odometry at (0, 0, 0): their frames look like their own, not one shared "
                    "frame, and their maps would be laid over each other wrongly; give each robot's odometry origin in the "
                    "shared frame (--initial-poses \"x,y,yaw;...\") or poses of one frame (a multi-robot SLAM's map)",
                    ", ".join(own))
    return [join(p, f"ROS 2 /{ns}") for p, ns in zip(parts, robots.names)]


class LiveDrive:
    """Sends the robots' scans as they come (see the module); ``pubs`` are the world's scan publishers."""

    def __init__(self, cfg: RunConfig, robots: RosRobots, team: Team, pubs: list, goals: Goals, bce: LatestBce):
        self.cfg, self.robots, self.team, self.pubs, self.goals, self.bce = cfg, robots, team, pubs, goals, bce
        n = cfg.robots
        self.seq = [0] * n
        self.held: list[tuple | None] = [None] * n  # (t, pose, angles, ranges, hit, reach, leg): its newest, not sent yet
        self.newest: list[tuple | None] = [None] * n  # its newest scan sent
        self.pose: list[np.ndarray | None] = [None] * n  # (x, y, yaw) of its newest scan
        self.t = 0.0  # seconds from the robots' first scan to the newest heard
        self.driven = [0.0] * n
        self.done = [False] * n
        self.why: dict[int, str] = {}
        self.t0 = min(float(r.log.t[r.train[0]]) for r in team.robots)
        self.exploring = cfg.explore.active
        grid = OccupancyGrid(np.zeros(team.shape, np.uint8), team.resolution, team.origin)
        self.coverage = TeamCoverage(grid, np.array([r.log.poses[r.train[0], :2] for r in team.robots]))
        self.curve: list[float] = []
        run_dir = cfg.run_dir if self.exploring else None
        self.out = RowLog(run_dir / "exploration.csv") if run_dir is not None else None
        self.goal_log = RowLog(run_dir / "goals.csv", GOAL_COLUMNS) if run_dir is not None else None

    # ------------------------------------------------------------------ scans
    def add(self, i: int, t: float, pose: np.ndarray, angles, ranges, hit, reach: float, leg: int | None) -> None:
        if self.held[i] is not None:
            self.send(i, self.held[i], end=False, last=False)
        self.held[i] = (t, pose, angles, ranges, hit, reach, leg)
        if self.pose[i] is not None:
            self.driven[i] += float(np.linalg.norm(pose[:2] - self.pose[i][:2]))
        self.pose[i], self.t = pose, max(self.t, t)
        self.coverage.add_scan(pose[:2], angles, ranges)
        if self.out is not None:
            self.out.row(i, t, float(pose[0]), float(pose[1]), self.driven[i], self.coverage.fraction(), self.bce.of(i))

    def add_log(self, i: int, part: LaserLog, scans: np.ndarray, leg: int | None) -> None:
        max_range = self.cfg.world.lidar_max_range_m
        ranges, hit, valid = part.hits(max_range)
        for k in scans:
            pose = part.poses[k]
            v = valid[k]
            self.add(i, float(part.t[k]) - self.t0, pose, (pose[2] + part.angles)[v], ranges[k][v], hit[k][v],
                     part.reach(max_range), leg)

    def feed(self, leg: int | None) -> None:
        """Every scan heard since the last feed, as part of ``leg``."""
        for i in range(self.cfg.robots):
            if self.done[i]:
                continue
            if (part := self.robots.take(i)) is not None:
                self.add_log(i, part, np.arange(len(part)), leg)

    def send(self, i: int, scan: tuple, end: bool, last: bool) -> None:
        t, pose, angles, ranges, hit, reach, leg = scan
        self.pubs[i].put(Scan(run=self.cfg.run_id, sender=i, seq=self.seq[i], t=t, pose=[float(v) for v in pose],
                              max_range=reach, angles=Tensor.of(angles.astype(np.float32), "<f4"),
                              ranges=Tensor.of(ranges.astype(np.float32), "<f4"), hit=Tensor.of(hit.astype(np.uint8), "|u1"),
                              last=last, leg=leg, leg_end=end))
        self.seq[i] += 1
        self.newest[i] = scan

    def close(self, i: int, leg: int | None, last: bool) -> None:
        """Robot ``i``'s held scan sent as the last of ``leg`` (and of its input); a robot silent since
        its previous one has that one sent again, marked."""
        scan = self.held[i]
        if scan is None:
            log.warning("robot %s: no scan came %s: its newest is sent again to mark it", self.robots.names[i],
                        f"during leg {leg}" if leg is not None else "since its last")
            scan = self.newest[i][:6] + (leg,)
        self.held[i] = None
        self.send(i, scan, end=leg is not None, last=last)
        self.done[i] = last

    # ------------------------------------------------------------------ the drive
    def start(self) -> None:
        """The warm-up's training scans and what came since: leg 0 when exploring."""
        leg = 0 if self.exploring else None
        for i, r in enumerate(self.team.robots):
            self.add_log(i, r.log, r.train, leg)
        self.feed(leg)
        if self.exploring:
            for i in range(self.cfg.robots):
                self.close(i, 0, last=False)

    def stream(self, stop: threading.Event) -> None:
        """Not exploring: every scan until the input is over."""
        s, start = self.cfg.ros2, time.monotonic()
        while not stop.is_set():
            self.feed(None)
            now = time.monotonic()
            if all(self.robots.silent_for(i, now) >= s.idle_s for i in range(self.cfg.robots)):
                log.info("the robots' input is over: none sent a scan for %.0f s (ros2.idle_s)", s.idle_s)
                break
            if now - start > s.max_input_s:
                log.warning("the input is over after %.0f s (ros2.max_input_s), though scans still come", s.max_input_s)
                break
            stop.wait(POLL_S)
        else:
            return
        for i in range(self.cfg.robots):
            self.close(i, None, last=True)

    def explore(self, stop: threading.Event) -> None:
        e = self.cfg.explore
        legs = self.cfg.legs()
        for leg in range(1, legs + 1):
            if stop.is_set() or all(self.done):
                break
            self.take_goals(leg, stop)
            until = time.monotonic() + e.leg_s
            while not stop.is_set() and time.monotonic() < until:
                self.feed(leg)
                for i in range(self.cfg.robots):
                    if not self.done[i] and i not in self.why and self.driven[i] >= e.distance_m:
                        self.end(i, f"distance budget of {e.distance_m:g} m driven")
                stop.wait(POLL_S)
            if stop.is_set():
                return
            self.feed(leg)
            self.leg_over(leg, legs)
            for i in range(self.cfg.robots):
                if not self.done[i]:
                    self.close(i, leg, last=i in self.why)
        for f in (self.out, self.goal_log):
            if f is not None:
                f.close()
        log.info("exploration (%s) over: coverage %.1f%% of the map's extent; driven %s m (team %.1f m); %s",
                 e.policy, 100 * self.coverage.fraction(), ", ".join(f"{d:.1f}" for d in self.driven), sum(self.driven),
                 "; ".join(f"robot {i}: {why}" for i, why in sorted(self.why.items())) or "stopped")

    def take_goals(self, leg: int, stop: threading.Event) -> None:
        """The driving robots' goals of ``leg``, sent on to them (scans heard meanwhile are of ``leg``)."""
        e = self.cfg.explore
        waiting = [i for i in range(self.cfg.robots) if not self.done[i]]
        deadline = time.monotonic() + e.goal_wait_s
        got: dict[int, Goal] = {}
        while not stop.is_set() and len(got) < len(waiting) and time.monotonic() < deadline:
            self.feed(leg)
            got = self.goals.wait({i: POLL_S for i in waiting}, leg, stop)
        for i in waiting:
            goal, (x, y, yaw) = got.get(i), self.pose[i]
            if goal is None:
                log.warning("robot %s: no goal for leg %d within %g s: it stays where it is", self.robots.names[i], leg,
                            e.goal_wait_s)
                self.robots.goal(i, x, y, yaw)
                continue
            if self.goal_log is not None:
                self.goal_log.row(i, leg, self.t, goal.x, goal.y, int(goal.done))
            if goal.done:
                self.end(i, f"nowhere left to go ({goal.reason or 'its policy says so'})")
            else:
                self.robots.goal(i, goal.x, goal.y, math.atan2(goal.y - y, goal.x - x))
                log.info("robot %s: leg %d goal (%.2f, %.2f) sent on /%s/goal_pose", self.robots.names[i], leg, goal.x,
                         goal.y, self.robots.names[i])

    def end(self, i: int, why: str) -> None:
        """Robot ``i``'s drive ends: it is sent its current pose as its goal (stay)."""
        if i not in self.why:
            self.why[i] = why
            self.robots.goal(i, *self.pose[i])

    def leg_over(self, leg: int, legs: int) -> None:
        e = self.cfg.explore
        if leg >= legs:
            for i in range(self.cfg.robots):
                self.end(i, f"the learners' last leg ({leg})")
        self.curve.append(self.coverage.fraction())
        if (why := stalled(self.curve, e.stall_legs, e.stall_gain)) is not None:
            for i in range(self.cfg.robots):
                self.end(i, why)


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The world service of ROS 2 robots; the exit status (2: refused, naming why)."""
    try:
        robots = RosRobots(cfg)
    except ConfigError as exc:
        log.error("%s", exc)
        return 2
    try:
        warm = warm_up(cfg, robots, stop)
        if warm is None:
            return 0
        w = cfg.world
        beams = cfg.labelling()
        team = make_team(warm, cfg.robots, max_range=w.lidar_max_range_m, resolution=w.grid_resolution_m,
                         holdout_every=w.dataset_holdout_every, margin=w.dataset_margin_m,
                         samples_per_beam=beams.samples_per_beam, occupied_depth=beams.occupied_depth_m,
                         val_beams=w.val_beams, extent=parse_extent(cfg.ros2.extent) if cfg.ros2.extent else None)
        describe(team)
        payload = encode(world_map_message(cfg, team))
        goals, bce = Goals(cfg.legs()), LatestBce()

        def listen(bus) -> None:
            if cfg.explore.active:
                bus.subscribe(bus.keys.goal("*"), Goal, goals.add)
                bus.subscribe(bus.keys.metrics("*"), Metrics, bce.add)

        with serving(cfg, lambda _parameters: payload, stop, listen) as pubs:
            if pubs is None:
                return 0
            drive = LiveDrive(cfg, robots, team, pubs, goals, bce)
            drive.start()
            drive.explore(stop) if cfg.explore.active else drive.stream(stop)
            stop.wait()  # keep serving the map until told to stop
        return 0
    except (ConfigError, DatasetError) as exc:
        log.error("%s", exc)
        return 2
    finally:
        robots.close(cfg.run_dir)
