"""A learner's part in exploration (``explore.policy``; the world's side: swarmmap.services.world.exploring).

At training round L x ``explore.decide_every`` (L = 1, 2, ... while the learners have rounds for
another leg) the learner chooses its robot's goal for leg L of the drive from what it trained on
(legs 0..L-1) and publishes it on ``learners/<id>/goal``, then waits for its robot's last scan of
leg L and trains on legs 0..L from then on (at most ``learner.window_scans`` scans, the newest).
Its goal passes over the goals that its lower-numbered neighbours hold for the same leg (it waits
for them up to ``explore.goal_wait_s``): each robot's choice depends on the seed and the data only,
never on which learner was quicker.

- ``uncertainty``: the model's mean and std (``explore.mc_samples`` passes, seeded by the leg) over
  the plan's bounds at ``explore.map_resolution_m``, cells where the robot's own scans ended
  marked occupied (a model that has not learned a wall yet must not send a robot through it),
  then :func:`~swarmmap.shared.world.explore.uncertainty_goal`.
- ``frontier``: a log-odds grid of its own and its neighbours' scans of legs 0..L-1, then
  :func:`~swarmmap.shared.world.explore.frontier_goal`.
- ``planned``: no goal; the learner only follows the legs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from swarmmap.services.learner.collector import Collector
from swarmmap.services.learner.node import Node
from swarmmap.shared.learning.bnn import predict_mean_std
from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.protocol import Goal, Scan, Tensor, WorldMap
from swarmmap.shared.world.explore import FREE_BELOW, Claims, Sensor, frontier_goal, uncertainty_goal
from swarmmap.shared.world.explore import Goal as Choice
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.logodds import LogOddsGrid, build_logodds
from swarmmap.shared.world.unseen import Coverage

log = logging.getLogger("learner")
Data = tuple[np.ndarray, np.ndarray]


class Explorer:
    """Robot ``robot``'s goals and the legs its learner trains on; ``node()`` is its learner's node (its network, and
    the cells its team has data on where it keeps them)."""

    def __init__(self, cfg: RunConfig, robot: int, bus: Bus, collector: Collector, neighbours: set[int],
                 node: Callable[[], Node], world: WorldMap):
        self.cfg, self.e, self.robot, self.collector, self.node = cfg, cfg.explore, robot, collector, node
        self.neighbours = sorted(neighbours)
        self.legs = cfg.legs()
        self.pub = bus.publisher(bus.keys.goal(robot))
        self.grid = OccupancyGrid(world.grid.numpy(), world.resolution, tuple(world.origin))
        self.centres, self.shape = self.grid.centres(self.e.map_resolution_m)  # the goal map's cells, once
        self.heard: dict[tuple[int, int], Goal] = {}
        self.scans: list[Scan] = []  # frontier: its own and its neighbours' scans since its last goal
        self.counts: LogOddsGrid | None = None  # frontier: the log-odds grid of those before
        self.ended: dict[int, int] = {}  # robot -> newest leg whose end its scans showed
        self.cond = threading.Condition()
        self.data: Data | None = None
        self.waited_s = self.choose_s = 0.0
        for j in self.neighbours:
            bus.subscribe(bus.keys.goal(j), Goal, self.add_goal)
        if self.e.policy == "frontier":
            for j in [robot, *self.neighbours]:
                bus.subscribe(bus.keys.scan(j), Scan, self.add_scan)

    def add_goal(self, msg: Goal) -> None:
        if msg.leg > self.legs:  # (no such leg: never kept)
            return
        with self.cond:
            self.heard.setdefault((msg.sender, msg.leg), msg)
            self.cond.notify_all()

    def add_scan(self, msg: Scan) -> None:
        with self.cond:
            self.scans.append(msg)
            if msg.leg is not None and (msg.leg_end or msg.last):
                self.ended[msg.sender] = max(self.ended.get(msg.sender, -1), msg.leg + (10**6 if msg.last else 0))
            self.cond.notify_all()

    def wait_for(self, ready: Callable[[], bool], stop: threading.Event) -> bool:
        """Wait (up to ``goal_wait_s``) until ``ready()``; False when it never was."""
        deadline = time.monotonic() + self.e.goal_wait_s
        with self.cond:
            while not ready() and not stop.is_set() and time.monotonic() < deadline:
                self.cond.wait(0.2)
            return ready()

    def window(self, k: int, stop: threading.Event) -> Data | None:
        """The training points of round ``k`` when they change (None: the same as before). At a
        leg's round: choose and publish the goal, wait for the leg, then its points."""
        every = self.e.decide_every
        if self.data is None:
            self.data = self.collector.arrays(self.cfg.learner.window_scans, through_leg=0)
            return self.data
        if k % every or not 1 <= k // every <= self.legs:
            return None
        leg = k // every
        if self.collector.done.is_set():  # its robot's drive is over: no wait, and a word its teammates need not wait for
            self.pub.put(Goal(run=self.cfg.run_id, sender=self.robot, leg=leg, round=k, done=True, reason="its drive is over"))
        else:
            t0 = time.monotonic()
            self.publish(leg, k, stop)
            self.choose_s += time.monotonic() - t0
            t0 = time.monotonic()
            if not self.collector.wait_leg(leg, self.e.goal_wait_s + self.cfg.learner.collect_timeout_s, stop):
                log.warning("robot %d: its scans of leg %d did not end within %.0f s: training on what came", self.robot,
                            leg, self.e.goal_wait_s + self.cfg.learner.collect_timeout_s)
            self.waited_s += time.monotonic() - t0
        self.data = self.collector.arrays(self.cfg.learner.window_scans, through_leg=leg)
        return self.data

    def publish(self, leg: int, k: int, stop: threading.Event) -> None:
        """Robot ``robot``'s goal for ``leg``, chosen after its lower-numbered neighbours' (theirs held apart);
        planned, its word that it reached the leg's round (the world drives each leg once its learners did)."""
        pose = np.asarray(self.collector.position or (0.0, 0.0), np.float64)
        if self.e.policy == "planned":
            self.pub.put(Goal(run=self.cfg.run_id, sender=self.robot, leg=leg, round=k, x=float(pose[0]), y=float(pose[1]),
                              path=Tensor.of(pose[None], "<f4"), reason="its planned path"))
            return
        before = [j for j in self.neighbours if j < self.robot]
        if not self.wait_for(lambda: all((j, leg) in self.heard for j in before), stop):
            log.warning("robot %d: goals of neighbour(s) %s for leg %d did not come within %.0f s: chosen without them "
                        "(this choice depends on timing)", self.robot, [j for j in before if (j, leg) not in self.heard],
                        leg, self.e.goal_wait_s)
        with self.cond:  # (its subscriptions add to what it heard meanwhile)
            claims = Claims({j: (g.x, g.y) for (j, g_leg), g in self.heard.items() if g_leg == leg and not g.done},
                            self.e.separation_m)
        choice = self.uncertainty(pose, claims, leg) if self.e.policy == "uncertainty" else self.frontier(pose, claims, leg, stop)
        run, me = self.cfg.run_id, self.robot
        if choice is None:
            msg = Goal(run=run, sender=me, leg=leg, round=k, x=float(pose[0]), y=float(pose[1]), done=True,
                       reason=f"no {self.e.policy} goal left")
        else:
            msg = Goal(run=run, sender=me, leg=leg, round=k, x=choice.xy[0], y=choice.xy[1],
                       path=Tensor.of(choice.path[:4096], "<f4"), reason=choice.reason[:200])
        log.info("robot %d: leg %d goal %s", me, leg, "none (done)" if msg.done else f"({msg.x:.2f}, {msg.y:.2f}): {msg.reason}")
        self.pub.put(msg)

    def sensor(self) -> Sensor:
        w = self.cfg.world
        return Sensor(beams=min(w.lidar_beams, 72), max_range=w.lidar_max_range_m)

    def uncertainty(self, pose: np.ndarray, claims: Claims, leg: int) -> Choice | None:
        e, res, node = self.e, self.e.map_resolution_m, self.node()
        pts, (h, w) = self.centres, self.shape
        mean, std = predict_mean_std(node.model, pts.astype(np.float32), samples=e.mc_samples, seed=leg)
        mean, std = mean.reshape(h, w).astype(np.float64), std.reshape(h, w)
        points, labels = self.data
        goal_grid = OccupancyGrid(np.zeros((h, w), np.uint8), res, self.grid.origin)
        hits, crossed = cells_of(goal_grid, points[labels > 0.5]), cells_of(goal_grid, points[labels <= 0.5])
        # What its own beams showed overrides what it learned so far: free where they crossed (a doorway its model
        # still blurs shut), a wall where they ended (a wall it has not learned yet).
        mean = np.where(ndimage.binary_dilation(crossed) & ~hits, np.minimum(mean, FREE_BELOW / 2), mean)
        mean[hits] = 1.0
        std = np.where(observed(goal_grid, points, pts, node.coverage), e.seen_weight * std, std)
        return uncertainty_goal(self.robot, pose, mean, std, self.grid.origin, res, claims, clearance=e.clearance_m,
                                sensor=self.sensor(), kind=e.information, min_gain=e.min_gain, min_travel=e.min_travel_m)

    def frontier(self, pose: np.ndarray, claims: Claims, leg: int, stop: threading.Event) -> Choice | None:
        """The nearest frontier of the log-odds grid of its team's scans of legs before ``leg``: the
        counts of the scans new since the last goal added to those kept (the scans themselves are not)."""
        team = [self.robot, *self.neighbours]
        self.wait_for(lambda: all(self.ended.get(j, -1) >= leg - 1 for j in team), stop)
        with self.cond:
            new = [s for s in self.scans if s.leg is not None and s.leg < leg]
            self.scans = [s for s in self.scans if s.leg is None or s.leg >= leg]
        if new:
            part = build_logodds(self.shape, self.grid.origin, self.e.map_resolution_m, np.array([s.pose[:2] for s in new]),
                                 np.stack([s.angles.numpy() for s in new]), np.stack([s.ranges.numpy() for s in new]),
                                 np.stack([s.hit.numpy().astype(bool) for s in new]))
            self.counts = part if self.counts is None else self.counts.plus(part)
        if self.counts is None:
            log.warning("robot %d: no scan of its own or its neighbours' heard before leg %d: no frontier", self.robot, leg)
            return None
        return frontier_goal(self.robot, pose, self.counts, claims, clearance=self.e.clearance_m,
                             min_travel=self.e.min_travel_m)


def cells_of(grid: OccupancyGrid, points: np.ndarray) -> np.ndarray:
    """(H, W) bool: the cells of ``grid`` holding some of ``points``."""
    out = np.zeros(grid.grid.shape, bool)
    rows, cols, inside = grid.cells(points)
    out[rows[inside], cols[inside]] = True
    return out


def observed(grid: OccupancyGrid, points: np.ndarray, centres: np.ndarray, coverage: Coverage | None) -> np.ndarray:
    """(H, W) bool: the cells of ``grid`` holding some of the robot's training ``points``, or (its
    prior's ``coverage``, with ``centres`` the grid's cell centres) that its teammates said they have data on."""
    out = cells_of(grid, points)
    if coverage is not None:
        c = np.floor((centres - coverage.origin) / coverage.cell).astype(np.int64)
        ok = (c[:, 1] >= 0) & (c[:, 1] < coverage.shape[0]) & (c[:, 0] >= 0) & (c[:, 0] < coverage.shape[1])
        theirs = np.zeros(len(centres), bool)
        theirs[ok] = coverage.others[c[ok, 1], c[ok, 0]]
        out |= theirs.reshape(out.shape)
    return out
