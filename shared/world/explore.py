"""Exploration: where a robot goes next, and how much of a building its team has seen.

A policy picks a robot's next goal from what it knows, given its pose and the goals its
teammates hold:

- ``uncertainty``: the robot's own current model gives occupancy mean and std over its map. The
  candidates are cells on a lattice that the model believes drivable (mean below 0.5, with the
  robot's clearance) and that a path on that believed map reaches; each is scored by the
  information a scan there would bring (the summed std, or predictive entropy, of the cells its
  beams would cross on the mean map, within LiDAR range and line of sight) per metre of path to
  it (:func:`uncertainty_goal`).
- ``frontier``: the classic (Yamauchi 1997; coordinated as Burgard et al. 2005): on a log-odds grid
  of the scans the robot heard (its own and its neighbours'), frontiers are known-free cells next
  to cells no beam reached; the goal is the nearest frontier cluster by path through known free
  space (:func:`frontier_goal`).
- ``planned``: the paths planned before the run (:func:`~swarmmap.shared.world.paths.plan_paths`).

Either way a goal within ``separation`` metres of one a teammate holds is not picked while
another is left (:class:`Claims`). :class:`TeamCoverage` judges a team's exploration on the
ground truth: the share of the reachable free space (free cells connected to where the robots
start) that any robot's beams have crossed.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph

from swarmmap.shared.run.sections import parse_starts  # noqa: F401 - starts are read where exploration is
from swarmmap.shared.world.grid import OccupancyGrid
from swarmmap.shared.world.logodds import LogOddsGrid
from swarmmap.shared.world.paths import GridPlanner, reachable_cells
from swarmmap.shared.world.sensing import along_beams, beam_angles

POLICIES = ("uncertainty", "frontier", "planned")
FREE_BELOW = 0.5  # a model's mean below this: believed free
KNOWN_FREE_BELOW = 0.5  # a log-odds cell below this probability (more beams crossed it than ended in it): known free


@dataclass(frozen=True)
class Sensor:
    """What a scan sees: ``beams`` over 360 degrees out to ``max_range`` metres."""

    beams: int = 72
    max_range: float = 3.5


@dataclass
class Claims:
    """The goals the robot's teammates hold (robot -> (x, y)), as they said them."""

    held: dict[int, tuple[float, float]] = field(default_factory=dict)
    separation: float = 1.5

    def free(self, points: np.ndarray, me: int) -> np.ndarray:
        """Which of ``points`` (K, 2) lie farther than ``separation`` from every teammate's goal."""
        others = np.array([xy for r, xy in self.held.items() if r != me], dtype=np.float64).reshape(-1, 2)
        if len(others) == 0:
            return np.ones(len(points), bool)
        d = np.linalg.norm(np.asarray(points, np.float64)[:, None, :] - others[None, :, :], axis=-1)
        return (d > self.separation).all(axis=1)


@dataclass(frozen=True)
class Goal:
    """A goal (metres, the plan's frame), the path to it on the map it was chosen on, and why."""

    xy: tuple[float, float]
    path: np.ndarray
    score: float
    reason: str


def start_cell(planner: GridPlanner, start: np.ndarray, within: float = 0.5) -> int | None:
    """The planner's cell of ``start``, or the nearest clear cell within ``within`` metres (a robot
    next to a wall, or where its model believes a wall); None when there is none."""
    cell = planner.cell(start)
    if planner.ok.ravel()[cell]:
        return cell
    dist, (rows, cols) = ndimage.distance_transform_edt(~planner.ok, return_indices=True)
    r, c = divmod(cell, planner.shape[1])
    if dist[r, c] * planner.grid.resolution > within:
        return None
    return int(rows[r, c] * planner.shape[1] + cols[r, c])


def path_costs(planner: GridPlanner, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Path length (metres, weighted away from walls) from ``start`` to every cell (inf where
    none), and each cell's predecessor on its path (for :func:`path_to`)."""
    cell = start_cell(planner, start)
    if cell is None:
        n = planner.shape[0] * planner.shape[1]
        return np.full(n, np.inf), np.full(n, -9999)
    return csgraph.dijkstra(planner.graph, indices=cell, return_predecessors=True)


def path_to(planner: GridPlanner, start: np.ndarray, pred: np.ndarray, goal_cell: int) -> np.ndarray:
    """The shortened path (K, 2) from ``start`` to ``goal_cell`` along :func:`path_costs`' predecessors."""
    cells = [goal_cell]
    while pred[cells[-1]] >= 0:
        cells.append(int(pred[cells[-1]]))
    pts = planner.xy(np.array(cells[::-1]))
    pts[0] = start
    return planner.shorten(pts)


def seen_cells(occupied: np.ndarray, origin: tuple[float, float], resolution: float, points: np.ndarray,
               sensor: Sensor, chunk: int = 32) -> np.ndarray:
    """(K, H*W) bool: the cells a scan from each of ``points`` would cross on the grid ``occupied``
    (H, W bool) within range, up to and including the first occupied cell of each beam."""
    h, w = occupied.shape
    grid = OccupancyGrid(occupied, resolution, origin)
    angles = beam_angles(sensor.beams)
    step = resolution / 2
    t = np.arange(0.0, sensor.max_range + step, step)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (B, 2)
    out = np.zeros((len(points), h * w), bool)
    for s in range(0, len(points), chunk):
        p = np.asarray(points[s : s + chunk], np.float64)
        pts = p[:, None, None, :] + t[None, None, :, None] * d[None, :, None, :]  # (n, B, T, 2)
        rows, cols, inside = grid.cells(pts)
        blocked = occupied[rows, cols] | ~inside
        before = np.cumsum(blocked, axis=2) - blocked  # occupied cells strictly before each step
        keep = inside & (before == 0)
        n, b, k = np.nonzero(keep)
        out[s + n, rows[n, b, k] * w + cols[n, b, k]] = True
    return out


def information(mean: np.ndarray, std: np.ndarray | None, kind: str = "std") -> np.ndarray:
    """What observing each cell is worth: its std, or its predictive entropy (bits) where ``kind`` is "entropy"."""
    if kind == "entropy" or std is None:
        p = np.clip(mean.astype(np.float64), 1e-6, 1 - 1e-6)
        return -(p * np.log2(p) + (1 - p) * np.log2(1 - p))
    return std.astype(np.float64)


def uncertainty_goal(me: int, pose: np.ndarray, mean: np.ndarray, std: np.ndarray | None, origin: tuple[float, float],
                     resolution: float, claims: Claims, *, clearance: float = 0.2, sensor: Sensor = Sensor(),
                     spacing: float = 0.5, travel_floor: float = 1.0, kind: str = "std", min_gain: float = 0.0,
                     min_travel: float = 0.0) -> Goal | None:
    """The believed-drivable cell whose scan would bring the most information per metre of path.

    ``mean`` and ``std`` (H, W) are the robot's model over the grid at ``origin``/``resolution``.
    The path runs on the believed map (mean >= FREE_BELOW occupied) with ``clearance``; candidates
    lie on a lattice every ``spacing`` metres, away from teammates' goals while any is left; the
    score is information / (path metres + ``travel_floor``); candidates nearer than ``min_travel``
    metres of path are passed over while another is left (a robot that stays sees nothing new).
    None when no candidate is reachable, or none would bring more than ``min_gain``.
    """
    occupied = mean >= FREE_BELOW
    planner = GridPlanner(OccupancyGrid(occupied.astype(np.uint8), resolution, origin), clearance)
    costs, pred = path_costs(planner, pose)
    every = max(1, round(spacing / resolution))
    lattice = np.zeros_like(occupied)
    lattice[every // 2 :: every, every // 2 :: every] = True
    cells = np.flatnonzero(lattice.ravel() & planner.ok.ravel() & np.isfinite(costs))
    if len(cells) == 0:
        return None
    points = planner.xy(cells)
    free = claims.free(points, me) & (costs[cells] >= min_travel)
    if free.any():
        cells, points = cells[free], points[free]
    gain = seen_cells(occupied, origin, resolution, points, sensor) @ information(mean, std, kind).ravel()
    score = np.where(gain > min_gain, gain / (costs[cells] + travel_floor), -np.inf)
    best = int(np.argmax(score))
    if not np.isfinite(score[best]):
        return None
    return Goal(tuple(map(float, points[best])), path_to(planner, pose, pred, int(cells[best])), float(score[best]),
                f"{kind} {gain[best]:.1f} over {costs[cells[best]]:.1f} m")


def frontier_goal(me: int, pose: np.ndarray, grid: LogOddsGrid, claims: Claims, *, clearance: float = 0.2,
                  min_cells: int = 4, min_travel: float = 0.0) -> Goal | None:
    """The nearest frontier cluster of ``grid`` by path through known free space.

    Frontier cells are known free (some beam crossed them, probability below KNOWN_FREE_BELOW)
    next to cells no beam reached; clusters of fewer than ``min_cells`` are noise. Each cluster's
    goal is its reachable cell nearest its centroid; clusters near a teammate's goal, or nearer than
    ``min_travel`` metres of path, are passed over while another is left. None when no frontier is reachable (the robot's map is closed).
    """
    known = grid.known()
    free = known & (grid.probability() < KNOWN_FREE_BELOW)
    frontier = free & ndimage.binary_dilation(~known, structure=np.ones((3, 3), bool))
    labels, n = ndimage.label(frontier, structure=np.ones((3, 3), bool))
    if n == 0:
        return None
    planner = GridPlanner(OccupancyGrid((~free).astype(np.uint8), grid.resolution, grid.origin), clearance)
    costs, pred = path_costs(planner, pose)
    reach = (np.isfinite(costs) & planner.ok.ravel()).reshape(free.shape)
    margin = math.ceil(clearance / grid.resolution) + 2  # (unknown space counts as a wall: a frontier is never clear itself)
    options = []
    for k in range(1, n + 1):
        cluster = labels == k
        cells = np.flatnonzero(cluster.ravel())
        if len(cells) < min_cells:
            continue
        near = np.flatnonzero((ndimage.binary_dilation(cluster, iterations=margin) & reach).ravel())
        if len(near) == 0:
            continue
        xy = planner.xy(near)
        centre = planner.xy(cells).mean(axis=0)
        pick = int(np.argmin(np.linalg.norm(xy - centre, axis=1)))
        options.append((float(costs[near[pick]]), int(near[pick]), xy[pick], len(cells)))
    if not options:
        return None
    points = np.array([o[2] for o in options])
    free_of_claims = claims.free(points, me) & (np.array([o[0] for o in options]) >= min_travel)
    if free_of_claims.any():
        options = [o for o, ok in zip(options, free_of_claims) if ok]
    cost, cell, xy, size = min(options, key=lambda o: (o[0], -o[3]))
    return Goal((float(xy[0]), float(xy[1])), path_to(planner, pose, pred, cell), -cost, f"frontier of {size} cells {cost:.1f} m away")


class TeamCoverage:
    """The share of a plan's reachable free space that any robot's beams have crossed, on the
    ground truth: free cells connected (8-way) to the robots' start cells."""

    def __init__(self, truth: OccupancyGrid, starts: np.ndarray):
        free = truth.grid == 0
        labels, _ = ndimage.label(free, structure=np.ones((3, 3), bool))
        r, c, inside = truth.cells(np.asarray(starts, np.float64))
        ids = {int(v) for v in labels[r[inside], c[inside]] if v > 0}
        self.truth = truth
        self.reachable = np.isin(labels, list(ids)) if ids else np.zeros_like(free)
        self.total = int(self.reachable.sum())
        self.seen = np.zeros_like(free)

    def add_scan(self, position: np.ndarray, angles: np.ndarray, ranges: np.ndarray) -> None:
        """Mark the cells the beams of one scan crossed (``angles`` absolute, ``ranges`` to each beam's end)."""
        r, c, inside = self.truth.cells(along_beams(position, angles, ranges, self.truth.resolution / 2))
        self.seen[r[inside], c[inside]] = True

    def fraction(self) -> float:
        return float((self.seen & self.reachable).sum() / self.total) if self.total else 0.0


def stalled(curve: list[float], legs: int, gain: float) -> str | None:
    """Why a team's drive ends on its coverage ``curve`` (a value per leg): it grew less than ``gain``
    over the last ``legs`` legs (``explore.stall_legs``, ``stall_gain``); None while it grows."""
    if len(curve) > legs and curve[-1] - curve[-1 - legs] < gain:
        return f"the team's coverage grew less than {gain:g} in {legs} legs"
    return None


def distance_at(coverage: np.ndarray, distance: np.ndarray, levels: tuple[float, ...] = (0.5, 0.8, 0.9, 0.95)
                ) -> dict[str, float | None]:
    """The team distance at which coverage first reached each level (None where never), from
    samples of (team distance, coverage) in time order."""
    out: dict[str, float | None] = {}
    for level in levels:
        reached = np.flatnonzero(np.asarray(coverage) >= level)
        out[f"{level:g}"] = round(float(np.asarray(distance)[reached[0]]), 3) if len(reached) else None
    return out


def spread_starts(truth: OccupancyGrid, robots: int, seed: int, clearance: float = 0.3) -> np.ndarray:
    """Start positions (robots, 2) spread over the largest clear region of the plan by the seed:
    a random first cell, then each next the clear cell farthest (straight line) from those taken."""
    planner = GridPlanner(truth, clearance)
    cells = np.flatnonzero(reachable_cells(planner))
    if len(cells) == 0:
        raise ValueError("the plan has no cell clear of walls by %.2f m to start a robot in" % clearance)
    xy = planner.xy(cells)
    rng = np.random.default_rng(seed)
    picked = [int(rng.integers(len(xy)))]
    for _ in range(robots - 1):
        d = np.min(np.linalg.norm(xy[:, None, :] - xy[picked][None, :, :], axis=-1), axis=1)
        picked.append(int(np.argmax(d)))
    return xy[picked]


EXPLORATION_COLUMNS = ("robot", "sim_time_s", "x", "y", "distance_m", "coverage", "val_bce")


GOAL_COLUMNS = ("robot", "leg", "sim_time_s", "x", "y", "done")


class RowLog:
    """A CSV file of ``columns`` appended and flushed row by row: a resumed run goes on where it
    was, a crash loses at most the row being written (:func:`read_rows` skips a torn last line).
    ``exploration.csv`` (:data:`EXPLORATION_COLUMNS`: one row per robot per scan, metres in the
    plan's frame, ``distance_m`` driven so far, ``coverage`` the team's so far, the robot's latest
    ``val_bce``) and ``goals.csv`` (:data:`GOAL_COLUMNS`: each goal the world drove a robot to)."""

    def __init__(self, path: Path | str, columns: tuple[str, ...] = EXPLORATION_COLUMNS):
        self.path = Path(path)
        fresh = not self.path.exists() or self.path.stat().st_size == 0
        self.file = self.path.open("a", encoding="utf-8", newline="")
        if fresh:
            self.file.write(",".join(columns) + "\n")
            self.file.flush()

    def row(self, *values: float | None) -> None:
        """One row: numbers (an empty field for None or a non-finite one)."""
        self.file.write(",".join("" if v is None or not math.isfinite(v) else f"{v:.7g}" if isinstance(v, float) else str(v)
                                 for v in values) + "\n")
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def read_exploration(path: Path | str, columns: tuple[str, ...] = EXPLORATION_COLUMNS) -> list[dict[str, float]]:
    """The rows of an ``exploration.csv`` (or a CSV of other ``columns``, as :class:`RowLog` writes
    them) as numbers, NaN where a field is empty (no val_bce yet), a torn last line skipped."""
    rows = []
    with Path(path).open(encoding="utf-8", newline="") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != columns:
            raise ValueError(f"{path}: not a CSV of {', '.join(columns)} (columns {reader.fieldnames})")
        for line in reader:
            if any(line[k] is None for k in columns):
                continue  # (a row cut short by a crash)
            try:
                rows.append({k: float(line[k]) if line[k] else math.nan for k in columns})
            except ValueError:
                continue
    return rows


def exploration_summary(rows: list[dict[str, float]], policy: str) -> dict:
    """``summary.json``'s ``exploration`` section from :func:`read_exploration`'s rows: each
    robot's distance, the team's, the final coverage and the team distance at which coverage first
    reached 0.5, 0.8, 0.9 and 0.95 (None where never)."""
    latest: dict[int, float] = {}
    team, cov = [], []
    for row in rows:
        latest[int(row["robot"])] = row["distance_m"]
        team.append(sum(latest.values()))
        cov.append(row["coverage"])
    return {"policy": policy, "robot_distance_m": {str(r): round(d, 3) for r, d in sorted(latest.items())},
            "team_distance_m": round(sum(latest.values()), 3), "final_coverage": round(cov[-1], 4) if cov else 0.0,
            "team_distance_at_coverage": distance_at(np.array(cov), np.array(team))}


def path_blocked(pose: np.ndarray, path: np.ndarray, hits: np.ndarray, clearance: float, lookahead: float) -> bool:
    """Whether the next ``lookahead`` metres of ``path`` from ``pose`` pass within ``clearance`` of a
    LiDAR return ``hits`` (K, 2): the learned map was wrong there, the robot must re-plan. Where
    the robot stands is not looked at (it is there already: a robot next to a wall may leave)."""
    if len(hits) == 0 or len(path) == 0:
        return False
    route = np.vstack([np.asarray(pose, np.float64)[None], path])
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    n = max(2, int(min(lookahead, seg.sum()) / (clearance / 2)) + 1)
    s = np.linspace(0.0, min(lookahead, seg.sum()), n)[1:]
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    frac = np.where(seg[i] > 0, (s - cum[i]) / np.where(seg[i] > 0, seg[i], 1.0), 0.0)
    pts = route[i] + frac[:, None] * (route[i + 1] - route[i])
    d = np.linalg.norm(pts[:, None, :] - np.asarray(hits, np.float64)[None, :, :], axis=-1)
    return bool((d < clearance).any())


@dataclass
class Drive:
    """A robot following its path at ``speed`` m/s of simulated time. Each step it looks at its
    real LiDAR first: a return within ``clearance`` of the path ahead stops it where it is
    (``blocked``; its policy re-plans with what the scan showed), so it never drives into a wall
    its learned map missed."""

    pose: np.ndarray
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    speed: float = 0.25
    clearance: float = 0.15
    lookahead: float = 0.6
    driven: float = 0.0
    blocked: bool = False

    def follow(self, path: np.ndarray) -> None:
        self.path, self.blocked = np.asarray(path, np.float64).reshape(-1, 2), False

    @property
    def arrived(self) -> bool:
        return len(self.path) == 0

    def step(self, dt: float, hits: np.ndarray) -> np.ndarray:
        """Move up to ``speed * dt`` metres along the path unless ``hits`` (the LiDAR returns seen
        from here, (K, 2) metres) block it; the new pose."""
        if self.arrived or self.blocked:
            return self.pose
        if path_blocked(self.pose, self.path, hits, self.clearance, self.lookahead):
            self.blocked = True
            return self.pose
        left = self.speed * dt
        while left > 0 and len(self.path):
            gap = float(np.linalg.norm(self.path[0] - self.pose))
            if gap <= left:
                self.pose, left, self.path = self.path[0].copy(), left - gap, self.path[1:]
                self.driven += gap
            else:
                self.pose = self.pose + (self.path[0] - self.pose) * (left / gap)
                self.driven += left
                left = 0.0
        return self.pose
