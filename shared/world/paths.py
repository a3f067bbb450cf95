"""Robot paths: planned through free space on the occupancy grid, or read from waypoint files.

:func:`plan_paths` picks a target in every room (its point farthest from walls; on a plan with
no room outlines, such as an occupancy image or a ROS map, targets that cover its free space:
:func:`coverage_targets`), spreads the robots' start rooms over the plan, and lets each robot
visit the nearest rooms that no teammate has visited yet (about twice its share, so tours
overlap); a room nobody reached is added to the tour that ends closest to it. Legs between
targets are shortest paths on the grid (8-connected, cells at least ``clearance`` from walls,
costs that keep robots away from walls), shortened where a straight line stays clear.
:func:`interpolate_dinno` smooths waypoint loops as DiNNO does; :func:`check_paths` refuses a
waypoint outside the map or inside a wall.
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from scipy import interpolate, ndimage, sparse
from scipy.sparse import csgraph
from shapely.ops import unary_union

from swarmmap.shared.world.floorplan import FloorPlan, OccupancyGrid, PlanError

NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def interpolate_dinno(waypoints: np.ndarray, per_segment: int = 30) -> np.ndarray:
    """DiNNO's trajectory: cubic interpolation over the waypoint index, ``per_segment`` points
    per segment (``interp1d(kind="cubic")`` of x and y)."""
    n = len(waypoints)
    if n < 4:
        return np.asarray(waypoints, dtype=np.float64)
    i = np.arange(n)
    s = np.linspace(0, n - 1, per_segment * (n - 1))
    x = interpolate.interp1d(i, waypoints[:, 0], kind="cubic")(s)
    y = interpolate.interp1d(i, waypoints[:, 1], kind="cubic")(s)
    return np.stack([x, y], axis=1)


def check_paths(paths: list[np.ndarray], grid: OccupancyGrid, source: object) -> None:
    """Refuse any path point outside the map or inside a wall, naming the path and the point."""
    x0, y0, x1, y1 = grid.bounds
    for r, path in enumerate(paths):
        if path.ndim != 2 or path.shape[1] != 2 or len(path) == 0 or not np.isfinite(path).all():
            raise PlanError(source, f"path {r}: waypoints must be a finite (K, 2) array, got shape {path.shape}")
        outside = (path[:, 0] < x0) | (path[:, 0] >= x1) | (path[:, 1] < y0) | (path[:, 1] >= y1)
        if outside.any():
            k = int(np.argmax(outside))
            raise PlanError(source, f"path {r}: waypoint {k} at ({path[k, 0]:.2f}, {path[k, 1]:.2f}) m lies outside "
                                    f"the map ({x0:.2f}..{x1:.2f}, {y0:.2f}..{y1:.2f})")
        inside = grid.occupied(path)
        if inside.any():
            k = int(np.argmax(inside))
            raise PlanError(source, f"path {r}: waypoint {k} at ({path[k, 0]:.2f}, {path[k, 1]:.2f}) m lies inside a wall")


class GridPlanner:
    """Shortest clear paths between points on an occupancy grid."""

    def __init__(self, grid: OccupancyGrid, clearance: float):
        self.grid = grid
        self.clearance_m = clearance
        self.clear = grid.clearance()
        ok = self.clear >= clearance
        labels, n = ndimage.label(ok, structure=np.ones((3, 3)))
        self.ok = ok
        self.labels = labels
        h, w = grid.grid.shape
        self.shape = (h, w)
        idx = np.arange(h * w).reshape(h, w)
        rows, cols, weights, steps = [], [], [], []
        res = grid.resolution
        penalty = 1.0 + 0.3 / np.maximum(self.clear, res)  # favour the middle of rooms and doors
        for dr, dc in NEIGHBOURS:
            a = ok[max(0, -dr) : h - max(0, dr), max(0, -dc) : w - max(0, dc)]
            b = ok[max(0, dr) : h - max(0, -dr), max(0, dc) : w - max(0, -dc)]
            both = a & b
            ia = idx[max(0, -dr) : h - max(0, dr), max(0, -dc) : w - max(0, dc)][both]
            ib = idx[max(0, dr) : h - max(0, -dr), max(0, dc) : w - max(0, -dc)][both]
            step = res * math.hypot(dr, dc)
            pa = penalty[max(0, -dr) : h - max(0, dr), max(0, -dc) : w - max(0, dc)][both]
            pb = penalty[max(0, dr) : h - max(0, -dr), max(0, dc) : w - max(0, -dc)][both]
            rows.append(ia)
            cols.append(ib)
            weights.append(step * (pa + pb) / 2)
            steps.append(np.full(len(ia), step))
        edges = (np.concatenate(rows), np.concatenate(cols))
        self.graph = sparse.csr_matrix((np.concatenate(weights), edges), shape=(h * w, h * w))
        self.lengths = sparse.csr_matrix((np.concatenate(steps), edges), shape=(h * w, h * w))  # plain metres

    def cell(self, xy: np.ndarray) -> int:
        r, c, _ = self.grid.cells(np.asarray(xy)[None])
        return int(r[0] * self.shape[1] + c[0])

    def xy(self, cells: np.ndarray) -> np.ndarray:
        r, c = np.divmod(np.asarray(cells), self.shape[1])
        res = self.grid.resolution
        return np.stack([self.grid.origin[0] + (c + 0.5) * res, self.grid.origin[1] + (r + 0.5) * res], axis=1)

    def segment_clear(self, a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(np.linalg.norm(b - a) / (self.grid.resolution / 2)) + 1)
        pts = a[None] + np.linspace(0, 1, n)[:, None] * (b - a)[None]
        r, c, inside = self.grid.cells(pts)
        return bool(inside.all() and self.ok[r, c].all())

    def shorten(self, pts: np.ndarray) -> np.ndarray:
        """Drop waypoints a straight clear line can skip."""
        out = [pts[0]]
        i = 0
        while i < len(pts) - 1:
            j = len(pts) - 1
            while j > i + 1 and not self.segment_clear(pts[i], pts[j]):
                j -= 1
            out.append(pts[j])
            i = j
        return np.asarray(out)


def reachable_cells(planner: GridPlanner) -> np.ndarray:
    """The cells of the largest connected clear region (bool grid): where robots can drive."""
    if not planner.ok.any():
        return planner.ok
    main = np.bincount(planner.labels[planner.ok]).argmax()
    return planner.ok & (planner.labels == main)


def coverage_targets(planner: GridPlanner, spacing: float, limit: int = 400) -> list[int]:
    """Targets that cover the reachable free space of a plan without room outlines (an occupancy
    image, a ROS map): farthest-point sampling in path distance (metres along the grid), so that
    every reachable cell lies within ``spacing`` metres of path from a target (the searches stop
    at twice that: a cell no target reaches within it counts as infinitely far, the first to be
    covered); each new target is moved to the clearest reachable cell near the farthest point
    (the middle of its room or corridor, not the wall it is near)."""
    reachable = reachable_cells(planner)
    if not reachable.any():
        return []
    flat_ok = reachable.ravel()
    clear = np.where(reachable, planner.clear, -1.0)
    targets = [int(clear.argmax())]
    reach = 2 * spacing  # a search stops there: beyond, the cells keep their distance to an older target (larger)

    def distances(cell: int) -> np.ndarray:
        return csgraph.dijkstra(planner.lengths, directed=False, indices=cell, limit=reach)

    dist = distances(targets[0])
    h, w = planner.shape
    half = max(1, int(spacing / 2 / planner.grid.resolution))
    while len(targets) < limit:
        gap = np.where(flat_ok, dist, -1.0)
        far = int(gap.argmax())
        if not gap[far] > spacing:  # (an unreachable cell never counts: it is not in flat_ok)
            break
        r, c = divmod(far, w)
        window = clear[max(0, r - half) : r + half + 1, max(0, c - half) : c + half + 1]
        wr, wc = np.unravel_index(int(window.argmax()), window.shape)
        target = (max(0, r - half) + wr) * w + max(0, c - half) + wc
        new = distances(target)
        if not new[far] < gap[far]:  # the clearest cell does not bring the farthest one closer
            target, new = far, distances(far)
        targets.append(int(target))
        dist = np.minimum(dist, new)
    return targets


def room_targets(plan: FloorPlan, planner: GridPlanner, coverage_spacing: float = 2.5,
                 rooms: list[int] | None = None) -> list[int]:
    """One reachable cell per room: the clearest one; rooms without a reachable cell are left out.
    With ``rooms`` (numbers in ``plan.rooms``) only those; robots then drive in the connected
    region that holds most of them (closed doors can cut a plan in parts), so the others stay
    unseen. A plan without room outlines (a raster plan, whose one "room" is the whole image)
    gets :func:`coverage_targets` instead, so that its robots drive through all of its free space."""
    if plan.raster is not None and len(plan.rooms) <= 1:
        targets = coverage_targets(planner, coverage_spacing)
        if len(targets) < 2:
            raise PlanError(plan.source, "no free space a robot can drive through: the reachable free region is smaller "
                                         f"than {coverage_spacing} m across (robots keep {planner.clearance_m} m from "
                                         "walls); check the map's scale and thresholds")
        return targets
    pts, shape = planner.grid.centres()
    chosen = list(range(len(plan.rooms))) if not rooms else sorted(set(rooms))
    bad = [r for r in chosen if not 0 <= r < len(plan.rooms)]
    if bad:
        raise PlanError(plan.source, f"room(s) {bad} do not exist: the plan has {len(plan.rooms)} rooms (0-{len(plan.rooms) - 1})")
    if rooms:  # the region (of cells a robot fits in) that holds most of the chosen rooms
        inside_any = shapely.contains_xy(unary_union([plan.rooms[r] for r in chosen]), pts[:, 0], pts[:, 1]).reshape(shape)
        labels = planner.labels[planner.ok & inside_any]
        if len(labels) == 0:
            raise PlanError(plan.source, f"rooms {chosen} have no space a robot fits in")
        reachable = planner.ok & (planner.labels == np.bincount(labels).argmax())
    else:
        reachable = reachable_cells(planner)
    targets = []
    for room in (plan.rooms[r] for r in chosen):
        inside = shapely.contains_xy(room, pts[:, 0], pts[:, 1]).reshape(shape) & reachable
        if inside.any():
            flat = np.where(inside.ravel(), planner.clear.ravel(), -1.0)
            targets.append(int(flat.argmax()))
    if not targets:
        raise PlanError(plan.source, "no room has free space a robot can reach")
    return targets


def plan_paths(plan: FloorPlan, grid: OccupancyGrid, robots: int, seed: int, rooms_per_robot: int = 0,
               clearance: float = 0.2, coverage_spacing: float = 2.5, rooms: list[int] | None = None) -> list[np.ndarray]:
    """One waypoint path (K, 2) in metres per robot; together they visit every reachable room
    (or, on a plan without room outlines, come within ``coverage_spacing`` of every reachable
    cell)."""
    planner = GridPlanner(grid, clearance)
    targets = room_targets(plan, planner, coverage_spacing, rooms)
    n = len(targets)
    dist, pred = csgraph.dijkstra(planner.graph, directed=False, indices=targets, return_predecessors=True)
    d = dist[:, targets]
    k = rooms_per_robot or min(n, max(2, math.ceil(2 * n / robots)))
    rng = np.random.default_rng(seed + 7919)
    starts = [int(rng.integers(n))]
    while len(starts) < min(robots, n):  # farthest-point spread of start rooms
        starts.append(int(np.argmax(d[starts].min(axis=0))))
    starts += [starts[r % n] for r in range(len(starts), robots)]
    covered: set[int] = set()
    tours: list[list[int]] = []
    for r in range(robots):
        tour = [starts[r]]
        covered.add(starts[r])
        while len(set(tour)) < k:
            here = tour[-1]
            options = [j for j in range(n) if j not in tour and np.isfinite(d[here, j])]
            if not options:
                break
            fresh = [j for j in options if j not in covered] or options
            tour.append(min(fresh, key=lambda j: d[here, j]))
            covered.add(tour[-1])
        tours.append(tour)
    for room in range(n):
        if room not in covered:
            best = min(range(robots), key=lambda r: d[tours[r][-1], room])
            tours[best].append(room)
            covered.add(room)
    paths = []
    for tour in tours:
        points = [planner.xy(np.array([targets[tour[0]]]))]
        for a, b in zip(tour, tour[1:]):
            leg = []
            cur = targets[b]
            while cur != targets[a] and cur >= 0:
                leg.append(cur)
                cur = pred[a, cur]
            # Shorten each leg on its own: a shortcut across legs would skip the rooms between.
            pts = planner.xy(np.asarray([targets[a]] + leg[::-1]))
            points.append(planner.shorten(pts)[1:])
        paths.append(np.concatenate(points))
    check_paths(paths, grid, plan.source)
    return paths


def coverage(paths: list[np.ndarray], grid: OccupancyGrid, radius: float) -> float:
    """Share of the free cells within ``radius`` (straight line; walls not considered) of a path:
    what the robots could scan, at most, with a LiDAR of that range."""
    near = np.zeros(grid.grid.shape, dtype=bool)
    for path in paths:
        if len(path) == 0:
            continue
        dense = [path[:1]]
        for a, b in zip(path[:-1], path[1:]):
            n = max(1, int(np.linalg.norm(b - a) / grid.resolution))
            dense.append(a + np.linspace(0, 1, n + 1)[1:, None] * (b - a))
        r, c, inside = grid.cells(np.concatenate(dense))
        near[r[inside], c[inside]] = True
    if not near.any():
        return 0.0
    within = ndimage.distance_transform_edt(~near) * grid.resolution <= radius
    free = grid.grid == 0
    return float((within & free).sum() / max(free.sum(), 1))


def path_length(path: np.ndarray) -> float:
    """Total length of a waypoint path in metres."""
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) if len(path) > 1 else 0.0


def point_along(path: np.ndarray, s: float) -> tuple[np.ndarray, float]:
    """Position and heading (rad) at arc length ``s`` along ``path`` (clamped to its ends)."""
    seg = np.diff(path, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    if len(seg) == 0 or lengths.sum() == 0:
        return path[0].copy(), 0.0
    s = float(np.clip(s, 0.0, lengths.sum()))
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    while lengths[i] == 0 and i > 0:
        i -= 1
    frac = (s - cum[i]) / lengths[i] if lengths[i] > 0 else 0.0
    return path[i] + frac * seg[i], math.atan2(seg[i][1], seg[i][0])
