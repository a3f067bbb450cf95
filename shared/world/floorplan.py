"""Floor plans in metres: walls, rooms and doors; their ground-truth occupancy grid and 3-D mesh.

World coordinates are metres, x right, y up. A :class:`FloorPlan` holds solid wall geometry
(walls, railings and windows, with door openings cut out) as shapely polygons, the rooms'
outlines and the doors; :meth:`FloorPlan.occupancy` rasterises it into an
:class:`OccupancyGrid` (outside the building occupied, as in DiNNO's data) and
:meth:`FloorPlan.mesh` extrudes the walls into a watertight triangle mesh. A raster plan (a
DiNNO occupancy PNG) carries its grid and derives its wall polygons from it. Plans come from
:func:`procedural` here, and from files through :mod:`swarmmap.shared.world.plans`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box
from shapely.ops import unary_union

from swarmmap.shared.world.grid import OccupancyGrid

if TYPE_CHECKING:
    import trimesh


def missing(path: object, what: str = "file") -> str:
    """A missing file's problem in words (``what`` ending in ":" is said as it is); one under a
    ``data`` folder in a folder named ``shared`` is the sample data kept beside the repository,
    and the words say where it comes from."""
    parts = Path(str(path)).parts
    sample = any(a == "shared" and b == "data" for a, b in zip(parts, parts[1:]))
    words = what[:-1] if what.endswith(":") else f"{what} does not exist"
    if sample:
        words += (" (sample data, kept beside the repository and never in it: the README's 'Sample data' says where "
                  "each comes from and where to put it)")
    return words


class PlanError(ValueError):
    """A floor-plan file that cannot be used; the message names the file and the problem."""

    def __init__(self, path: object, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


@dataclass
class FloorPlan:
    """Solid walls (doors cut out), free rooms, door openings, and optional waypoint paths.

    ``kind`` is ``procedural``, ``cubicasa``, ``dinno`` or ``rosmap``; a raster plan (``dinno``,
    ``rosmap``) carries its ground-truth grid in ``raster``."""

    name: str
    source: str
    walls: Polygon | MultiPolygon
    rooms: list[Polygon] = field(default_factory=list)
    room_names: list[str] = field(default_factory=list)
    doors: list[Polygon] = field(default_factory=list)
    raster: OccupancyGrid | None = None
    paths: list[np.ndarray] | None = None
    kind: str = "procedural"
    image_size: tuple[int, int] | None = None  # raster plans: (width, height) in pixels
    closed: list[int] = field(default_factory=list)  # doors closed (numbers in the plan's original door list)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of walls and rooms."""
        if self.raster is not None:
            return self.raster.bounds
        geoms = [self.walls, *self.rooms]
        return tuple(unary_union(geoms).bounds)  # type: ignore[return-value]

    def wall_parts(self) -> list[Polygon]:
        """The wall geometry as a list of polygons (with holes)."""
        geom = self.walls
        return list(geom.geoms) if isinstance(geom, MultiPolygon) else [geom] if not geom.is_empty else []

    def occupancy(self, resolution: float, margin: float = 0.5) -> OccupancyGrid:
        """The ground truth at ``resolution``: walls and outside occupied, rooms, doors and any
        region enclosed by walls free."""
        if self.raster is not None:
            return self.raster.resample(resolution)
        xmin, ymin, xmax, ymax = self.bounds
        origin = (xmin - margin, ymin - margin)
        width = int(math.ceil((xmax - xmin + 2 * margin) / resolution))
        height = int(math.ceil((ymax - ymin + 2 * margin) / resolution))
        grid = OccupancyGrid(np.ones((height, width), dtype=np.uint8), resolution, origin)
        pts, shape = grid.centres()
        x, y = pts[:, 0], pts[:, 1]
        wall = shapely.contains_xy(self.walls, x, y).reshape(shape)
        free = np.zeros(shape, dtype=bool)
        if self.rooms:
            free |= shapely.contains_xy(unary_union(self.rooms), x, y).reshape(shape)
        if self.doors:
            free |= shapely.contains_xy(unary_union(self.doors), x, y).reshape(shape)
        # Space enclosed by walls but outside every room outline is free too.
        from scipy import ndimage  # here: every service reads plans' types, few label them

        labels, _ = ndimage.label(~wall)
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        free |= ~np.isin(labels, border) & ~wall
        free &= ~wall
        grid.grid[free] = 0
        return grid

    def mesh(self, height: float) -> trimesh.Trimesh:
        """The walls extruded to ``height`` metres: one watertight mesh."""
        import trimesh  # here: only the world builds meshes, and trimesh costs every learner 0.5 s and memory

        # Snapping to a micrometre grid and dropping collinear vertices keeps the triangulation
        # of rings with many mitred corners from leaving gaps (a non-watertight mesh).
        clean = [shapely.set_precision(p, 1e-6).simplify(1e-6) for p in self.wall_parts() if p.area > 1e-8]
        parts = [trimesh.creation.extrude_polygon(p, height) for p in clean if not p.is_empty]
        if not parts:
            raise PlanError(self.source, "the plan has no walls to extrude")
        return trimesh.util.concatenate(parts)


def close_doors(plan: FloorPlan, fraction: float = 0.0, named: list[int] | None = None, seed: int = 0) -> list[int]:
    """Close doors of ``plan`` in place: the ones numbered in ``named`` (their order in
    ``plan.doors``) and, of the rest, a seeded ``fraction`` (rounded to the nearest count). A
    closed door is wall again, so the rooms behind it can stay unseen. Returns the closed doors'
    numbers; a number that names no door raises PlanError."""
    named = sorted(set(named or []))
    bad = [d for d in named if not 0 <= d < len(plan.doors)]
    if bad:
        raise PlanError(plan.source, f"door(s) {bad} do not exist: the plan has {len(plan.doors)} doors (0-{len(plan.doors) - 1})")
    rest = [d for d in range(len(plan.doors)) if d not in named]
    count = int(round(fraction * len(rest)))
    picked = sorted(named + [int(d) for d in np.random.default_rng(seed + 60013).permutation(rest)[:count]])
    if picked:
        # a little wider than the opening: the wall closes flush on both sides
        plan.walls = unary_union([plan.walls, *[plan.doors[d].buffer(0.01, join_style="mitre") for d in picked]])
        plan.doors = [door for d, door in enumerate(plan.doors) if d not in picked]
    return picked


Edge = tuple[int, int, bool, float, float, float]  # a possible door: cells a, b, vertical?, position across, lo, hi along


def procedural(rooms_x: int, rooms_y: int, seed: int, *, room_min: float = 2.5, room_max: float = 4.5,
               wall_thickness: float = 0.12, door_width: float = 0.9, extra_door_prob: float = 0.3,
               corridor_width: float = 1.3) -> FloorPlan:
    """A seeded CubiCasa-like apartment: ``rooms_y`` rows of ``rooms_x`` rooms with a corridor
    between the middle rows (``corridor_width`` 0: none). Rooms on the corridor open onto it;
    the others open towards it; neighbours in a row get a door with ``extra_door_prob`` (and
    always where the rooms would otherwise not be connected, as without a corridor)."""
    rng = np.random.default_rng(seed)
    t = wall_thickness
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(room_min, room_max, rooms_x))])
    heights = list(rng.uniform(room_min, room_max, rooms_y))
    split = rooms_y // 2 if rooms_y > 1 else 0  # rows below the corridor
    bands: list[tuple[str, float]] = [("row", h) for h in heights[:split]]
    if corridor_width > 0:
        bands.append(("corridor", corridor_width))
    bands += [("row", h) for h in heights[split:]]
    ys = np.concatenate([[0.0], np.cumsum([h for _, h in bands])])
    cells, grid_ids, corridor = _cells(bands, xs, ys, rooms_x)
    chosen = _doorways(rng, bands, xs, ys, grid_ids, corridor, len(cells), rooms_x, rooms_y, split, extra_door_prob)
    doors = []
    slack = door_width / 2 + t / 2 + 0.15
    for a, b_, vertical_edge, across, lo, hi in chosen:
        if hi - lo < 2 * slack:
            continue
        c = rng.uniform(lo + slack, hi - slack)
        w = door_width / 2
        doors.append(box(across - t, c - w, across + t, c + w) if vertical_edge else box(c - w, across - t, c + w, across + t))
    frames = [cell.exterior.buffer(t / 2, cap_style="square", join_style="mitre") for _, cell in cells]
    walls = unary_union(frames).difference(unary_union(doors)) if doors else unary_union(frames)
    rooms = [cell.buffer(-t / 2, join_style="mitre") for _, cell in cells]
    name = f"procedural-{rooms_x}x{rooms_y}-seed{seed}"
    return FloorPlan(name, f"procedural:{rooms_x}x{rooms_y}:seed{seed}", walls, rooms, [n for n, _ in cells], doors)


def _cells(bands: list[tuple[str, float]], xs: np.ndarray, ys: np.ndarray, rooms_x: int
           ) -> tuple[list[tuple[str, Polygon]], dict[tuple[int, int], int], int]:
    """The plan's cells (rooms by row and column, the corridor), each room's cell index, the corridor's (-1: none)."""
    cells: list[tuple[str, Polygon]] = []
    grid_ids: dict[tuple[int, int], int] = {}
    corridor = -1
    row = 0
    for band, (kind, _) in enumerate(bands):
        if kind == "corridor":
            corridor = len(cells)
            cells.append(("corridor", box(xs[0], ys[band], xs[-1], ys[band + 1])))
            continue
        for i in range(rooms_x):
            grid_ids[(i, row)] = len(cells)
            cells.append((f"room-{row}-{i}", box(xs[i], ys[band], xs[i + 1], ys[band + 1])))
        row += 1
    return cells, grid_ids, corridor


def _doorways(rng: np.random.Generator, bands, xs, ys, grid_ids, corridor: int, n_cells: int, rooms_x: int, rooms_y: int,
              split: int, extra_door_prob: float) -> list[Edge]:
    """The shared edges that get a door: every room towards the corridor, then, in a random order,
    each other edge that connects what is not yet connected, or with ``extra_door_prob``."""
    band_of_row = [b for b, (kind, _) in enumerate(bands) if kind == "row"]
    edges: list[Edge] = []
    for r in range(rooms_y):
        b = band_of_row[r]
        for i in range(1, rooms_x):
            edges.append((grid_ids[(i - 1, r)], grid_ids[(i, r)], True, xs[i], ys[b], ys[b + 1]))
    chosen: list[Edge] = []
    parent = list(range(n_cells))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    def join(e: Edge) -> None:
        parent[find(e[0])] = find(e[1])
        chosen.append(e)

    if corridor >= 0:
        for e in _towards_corridor(bands, band_of_row, xs, ys, grid_ids, corridor, rooms_x, rooms_y, split):
            join(e)
    vertical = [(grid_ids[(i, r - 1)], grid_ids[(i, r)], False, ys[band_of_row[r]], xs[i], xs[i + 1])
                for r in range(1, rooms_y) for i in range(rooms_x)] if corridor < 0 else []
    candidates = edges + vertical
    for k in rng.permutation(len(candidates)):
        e = candidates[k]
        if find(e[0]) != find(e[1]) or rng.uniform() < extra_door_prob:
            join(e)
    return chosen


def _towards_corridor(bands, band_of_row, xs, ys, grid_ids, corridor: int, rooms_x: int, rooms_y: int, split: int
                      ) -> list[Edge]:
    """A door for every room: onto the corridor where it lies beside it, else towards it."""
    out: list[Edge] = []
    for r in range(rooms_y):
        for i in range(rooms_x):
            b = band_of_row[r]
            if b + 1 < len(bands) and bands[b + 1][0] == "corridor":
                out.append((grid_ids[(i, r)], corridor, False, ys[b + 1], xs[i], xs[i + 1]))
            elif b > 0 and bands[b - 1][0] == "corridor":
                out.append((grid_ids[(i, r)], corridor, False, ys[b], xs[i], xs[i + 1]))
            else:  # further out: a door towards the corridor
                toward = r + 1 if b < band_of_row[split] else r - 1
                nb = band_of_row[toward]
                out.append((grid_ids[(i, r)], grid_ids[(i, toward)], False, ys[max(b, nb)], xs[i], xs[i + 1]))
    return out
