"""Floor plans in metres: walls, rooms and doors; their ground-truth occupancy grid; robot paths.

World coordinates are metres, x right, y up. A :class:`FloorPlan` is a set of solid wall boxes
(the 3-D world extrudes them) and free rooms joined by doors; :meth:`FloorPlan.occupancy`
rasterises it into an :class:`OccupancyGrid` whose outside is occupied, as in DiNNO's data.
:func:`procedural` makes a seeded apartment; :func:`plan_paths` routes robots from different
start rooms through doors so that together they cover the plan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


class PlanError(ValueError):
    """A floor-plan file that cannot be used; the message names the file and the problem."""

    def __init__(self, path: object, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle [x0, x1] x [y0, y1] in metres."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def centre(self) -> tuple[float, float]:
        return (self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2


@dataclass(frozen=True)
class Door:
    """An opening between rooms ``a`` and ``b``: its centre, its normal (unit, from a to b) and width."""

    a: int
    b: int
    centre: tuple[float, float]
    normal: tuple[float, float]
    width: float


@dataclass
class FloorPlan:
    """Solid walls, free rooms and the doors between them."""

    walls: list[Rect]
    rooms: list[Rect]
    doors: list[Door]
    wall_thickness: float
    name: str = "plan"
    openings: list[Rect] = field(default_factory=list)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) over all walls."""
        xs0, ys0, xs1, ys1 = zip(*[(w.x0, w.y0, w.x1, w.y1) for w in self.walls])
        return min(xs0), min(ys0), max(xs1), max(ys1)

    def occupancy(self, resolution: float, margin: float = 0.5) -> OccupancyGrid:
        """Rasterise: rooms and door openings free, everything else (walls, outside) occupied."""
        xmin, ymin, xmax, ymax = self.bounds
        origin = (xmin - margin, ymin - margin)
        width = int(math.ceil((xmax - xmin + 2 * margin) / resolution))
        height = int(math.ceil((ymax - ymin + 2 * margin) / resolution))
        grid = OccupancyGrid(np.ones((height, width), dtype=np.uint8), resolution, origin)
        for rect in self.rooms + self.openings:
            grid.fill(rect, 0)
        for rect in self.walls:
            grid.fill(rect, 1)
        return grid


@dataclass
class OccupancyGrid:
    """``grid[r, c]`` (1 = occupied) covers x in [ox + c*res, +res), y in [oy + r*res, +res)."""

    grid: np.ndarray
    resolution: float
    origin: tuple[float, float]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        h, w = self.grid.shape
        return self.origin[0], self.origin[1], self.origin[0] + w * self.resolution, self.origin[1] + h * self.resolution

    def _span(self, lo: float, hi: float, o: float, n: int) -> tuple[int, int]:
        # Cells whose centres lie inside [lo, hi].
        a = int(math.ceil((lo - o) / self.resolution - 0.5))
        b = int(math.floor((hi - o) / self.resolution - 0.5)) + 1
        return max(a, 0), min(b, n)

    def fill(self, rect: Rect, value: int) -> None:
        """Set every cell whose centre lies in ``rect``."""
        h, w = self.grid.shape
        c0, c1 = self._span(rect.x0, rect.x1, self.origin[0], w)
        r0, r1 = self._span(rect.y0, rect.y1, self.origin[1], h)
        if c0 < c1 and r0 < r1:
            self.grid[r0:r1, c0:c1] = value

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, inside) of points ``xy`` (..., 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        cols = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        rows = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        h, w = self.grid.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        return np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1), inside

    def occupied(self, xy: np.ndarray) -> np.ndarray:
        """Occupancy (bool) at points ``xy`` (..., 2); outside the grid counts as occupied."""
        rows, cols, inside = self.cells(xy)
        return (self.grid[rows, cols] > 0) | ~inside

    def centres(self, resolution: float | None = None) -> tuple[np.ndarray, tuple[int, int]]:
        """Points (H*W, 2) on a grid over the bounds at ``resolution`` (row-major, y up), and (H, W)."""
        res = resolution or self.resolution
        x0, y0, x1, y1 = self.bounds
        xs = np.arange(x0 + res / 2, x1, res)
        ys = np.arange(y0 + res / 2, y1, res)
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx.ravel(), gy.ravel()], axis=1), (len(ys), len(xs))

    def random_free(self, n: int, rng: np.random.Generator, clearance: float = 0.0) -> np.ndarray:
        """``n`` points drawn uniformly from free cells at least ``clearance`` from anything occupied."""
        free = self.grid == 0
        if clearance > 0:
            k = int(math.ceil(clearance / self.resolution))
            padded = np.pad(self.grid > 0, k, constant_values=True)
            near = np.zeros_like(free)
            h, w = free.shape
            for dr in range(-k, k + 1):
                for dc in range(-k, k + 1):
                    if dr * dr + dc * dc <= k * k:
                        near |= padded[k + dr : k + dr + h, k + dc : k + dc + w]
            free &= ~near
        rows, cols = np.nonzero(free)
        if len(rows) == 0:
            raise ValueError("the occupancy grid has no free cell" + (f" {clearance} m from a wall" if clearance else ""))
        pick = rng.integers(0, len(rows), size=n)
        jitter = rng.uniform(0, 1, size=(n, 2))
        x = self.origin[0] + (cols[pick] + jitter[:, 0]) * self.resolution
        y = self.origin[1] + (rows[pick] + jitter[:, 1]) * self.resolution
        return np.stack([x, y], axis=1)


def procedural(rooms_x: int, rooms_y: int, seed: int, *, room_min: float = 2.5, room_max: float = 4.5,
               wall_thickness: float = 0.12, door_width: float = 0.9, extra_door_prob: float = 0.3) -> FloorPlan:
    """A seeded apartment of ``rooms_x`` x ``rooms_y`` rooms joined by doors (a random spanning
    tree, so every room is reachable, plus extra doors with probability ``extra_door_prob``)."""
    rng = np.random.default_rng(seed)
    t = wall_thickness
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(room_min, room_max, rooms_x))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(room_min, room_max, rooms_y))])

    def rid(i: int, j: int) -> int:
        return j * rooms_x + i

    rooms = [Rect(xs[i] + t / 2, ys[j] + t / 2, xs[i + 1] - t / 2, ys[j + 1] - t / 2)
             for j in range(rooms_y) for i in range(rooms_x)]
    # Candidate doors: every wall between two neighbouring rooms.
    edges = [(rid(i, j), rid(i + 1, j)) for j in range(rooms_y) for i in range(rooms_x - 1)]
    edges += [(rid(i, j), rid(i, j + 1)) for j in range(rooms_y - 1) for i in range(rooms_x)]
    order = rng.permutation(len(edges))
    parent = list(range(len(rooms)))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    chosen = []
    for k in order:  # randomised Kruskal: a spanning tree, then extra doors
        a, b = edges[k]
        if find(a) != find(b):
            parent[find(a)] = find(b)
            chosen.append(edges[k])
        elif rng.uniform() < extra_door_prob:
            chosen.append(edges[k])
    door_on = set(chosen)

    walls = [Rect(xs[0] - t / 2, ys[0] - t / 2, xs[-1] + t / 2, ys[0] + t / 2),
             Rect(xs[0] - t / 2, ys[-1] - t / 2, xs[-1] + t / 2, ys[-1] + t / 2),
             Rect(xs[0] - t / 2, ys[0] - t / 2, xs[0] + t / 2, ys[-1] + t / 2),
             Rect(xs[-1] - t / 2, ys[0] - t / 2, xs[-1] + t / 2, ys[-1] + t / 2)]
    doors: list[Door] = []
    openings: list[Rect] = []
    slack = door_width / 2 + t / 2 + 0.15

    def wall_with_door(a: int, b: int, along0: float, along1: float, across: float, vertical: bool) -> None:
        if (a, b) not in door_on:
            segs = [(along0 - t / 2, along1 + t / 2)]
        else:
            c = rng.uniform(along0 + slack, along1 - slack)
            segs = [(along0 - t / 2, c - door_width / 2), (c + door_width / 2, along1 + t / 2)]
            centre = (across, c) if vertical else (c, across)
            normal = (1.0, 0.0) if vertical else (0.0, 1.0)
            doors.append(Door(a, b, centre, normal, door_width))
            lo, hi = c - door_width / 2, c + door_width / 2
            openings.append(Rect(across - t, lo, across + t, hi) if vertical else Rect(lo, across - t, hi, across + t))
        for s0, s1 in segs:
            walls.append(Rect(across - t / 2, s0, across + t / 2, s1) if vertical else Rect(s0, across - t / 2, s1, across + t / 2))

    for j in range(rooms_y):
        for i in range(1, rooms_x):
            wall_with_door(rid(i - 1, j), rid(i, j), ys[j], ys[j + 1], xs[i], vertical=True)
    for j in range(1, rooms_y):
        for i in range(rooms_x):
            wall_with_door(rid(i, j - 1), rid(i, j), xs[i], xs[i + 1], ys[j], vertical=False)
    return FloorPlan(walls, rooms, doors, t, name=f"procedural-{rooms_x}x{rooms_y}-seed{seed}", openings=openings)


def plan_paths(plan: FloorPlan, robots: int, seed: int, rooms_per_robot: int = 0,
               approach: float = 0.45) -> list[np.ndarray]:
    """One waypoint path (K, 2) per robot: a depth-first tour through doors from a start room.

    Start rooms are spread over the plan; each robot visits ``rooms_per_robot`` rooms (0: about
    twice the plan's share, so that tours overlap), preferring rooms no teammate has visited;
    a room that no tour reached is then added to the tour that ends closest to it, so the team
    covers every reachable room. Doors are crossed straight, between points ``approach`` metres
    either side of the door.
    """
    n = len(plan.rooms)
    k = rooms_per_robot or min(n, max(2, math.ceil(2 * n / robots)))
    door_between: dict[tuple[int, int], Door] = {}
    adjacency: dict[int, list[int]] = {i: [] for i in range(n)}
    for d in plan.doors:
        if (d.a, d.b) not in door_between:
            door_between[(d.a, d.b)] = door_between[(d.b, d.a)] = d
            adjacency[d.a].append(d.b)
            adjacency[d.b].append(d.a)
    rng = np.random.default_rng(seed + 7919)
    covered: set[int] = set()
    walks: list[list[int]] = []
    for r in range(robots):
        start = (r * n // robots) % n if robots <= n else r % n
        walk, visited, stack = [start], {start}, [start]
        while stack and len(visited) < k:
            options = [b for b in adjacency[stack[-1]] if b not in visited]
            if options:
                fresh = [b for b in options if b not in covered] or options
                nxt = fresh[rng.integers(len(fresh))]
                visited.add(nxt)
                stack.append(nxt)
                walk.append(nxt)
            else:
                stack.pop()
                if stack:
                    walk.append(stack[-1])  # walk back through the door we came by
        covered |= visited
        walks.append(walk)
    for room in range(n):
        if room in covered:
            continue
        routes = [_route(adjacency, w[-1], room) for w in walks]
        best = min((len(rt), i) for i, rt in enumerate(routes) if rt is not None) if any(routes) else None
        if best is None:
            continue  # unreachable from every start: nobody can map it
        walks[best[1]].extend(routes[best[1]][1:])
        covered |= set(routes[best[1]])
    paths = []
    for r, walk in enumerate(walks):
        cx, cy = plan.rooms[walk[0]].centre
        offset = 0.3 * (r // n) if robots > n else 0.0  # robots sharing a start room start apart
        points = [(cx + offset, cy)]
        for here, nxt in zip(walk, walk[1:]):
            door = door_between[(here, nxt)]
            sign = 1.0 if door.a == here else -1.0
            (x, y), (nx, ny) = door.centre, door.normal
            points.append((x - sign * nx * approach, y - sign * ny * approach))
            points.append((x + sign * nx * approach, y + sign * ny * approach))
            points.append(plan.rooms[nxt].centre)
        paths.append(np.asarray(points, dtype=np.float64))
    return paths


def _route(adjacency: dict[int, list[int]], a: int, b: int) -> list[int] | None:
    """Shortest room sequence from ``a`` to ``b`` (breadth-first), or None."""
    prev = {a: a}
    todo = [a]
    for here in todo:
        if here == b:
            out = [b]
            while out[-1] != a:
                out.append(prev[out[-1]])
            return out[::-1]
        for nxt in adjacency[here]:
            if nxt not in prev:
                prev[nxt] = here
                todo.append(nxt)
    return None


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
