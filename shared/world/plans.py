"""Floor plans from every source behind one spec: ``procedural``, a CubiCasa5K ``model.svg``, a
DiNNO occupancy PNG (with its waypoint ``.npy`` loops), or a ROS ``map_server`` map (its
``.yaml``, with unknown cells).

    plan = load_floorplan("../shared/data/cubicasa5k/353/model.svg", cfg.world, seed=0)
    plan = load_floorplan("floor_img.png", cfg.world, seed=0)   # + world.waypoints = a folder of .npy

A PNG is read as DiNNO does: 255 (>= 128) is occupied, a border of ``dinno_border_px`` pixels
is forced occupied, ``pixels_per_metre`` sets the scale, the image centre is the origin and
image rows grow southwards. Its waypoint files hold (K, 2) loops in DiNNO's normalised
[-1, 1] coordinates, scaled by (width/2, height/2) pixels and interpolated as DiNNO does.
Waypoint files for the other kinds hold metres. Every problem raises :class:`PlanError`
naming the file.
"""

from __future__ import annotations

import hashlib
import io
import logging
import math
import re
from pathlib import Path

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from swarmmap.shared.run.config import RunConfig, WorldSettings
from swarmmap.shared.world.floorplan import FloorPlan, OccupancyGrid, PlanError, close_doors, missing, procedural

MAX_IMAGE_PIXELS = 50_000_000
MAX_IMAGE_BYTES = 256 << 20
log = logging.getLogger(__name__)


def plan_reference(spec: str) -> dict[str, str]:
    """What identifies a plan in a recording: its spec and, for a file, its SHA-256."""
    if spec == "procedural":
        return {"floorplan": spec}
    data = Path(spec).read_bytes()
    return {"floorplan": str(Path(spec).resolve()), "sha256": hashlib.sha256(data).hexdigest()}


def load_floorplan(spec: str, settings: WorldSettings, seed: int) -> FloorPlan:
    """The plan named by ``spec`` (``procedural`` or a path ending .svg or .png), with its
    waypoint paths when ``settings.waypoints`` names them."""
    if spec == "procedural":
        plan = procedural(settings.rooms_x, settings.rooms_y, seed, room_min=settings.room_min_m,
                          room_max=settings.room_max_m, wall_thickness=settings.wall_thickness_m,
                          door_width=settings.door_width_m, extra_door_prob=settings.extra_door_prob,
                          corridor_width=settings.corridor_width_m)
    else:
        path = Path(spec)
        if not path.is_file():
            raise PlanError(spec, missing(path) if not path.exists() else "not a regular file")
        suffix = path.suffix.lower()
        if suffix == ".svg":
            plan = load_cubicasa_plan(path)
        elif suffix == ".png":
            plan = load_dinno_png(path, settings.pixels_per_metre, settings.dinno_border_px, settings.grid_resolution_m)
        elif suffix in (".yaml", ".yml"):
            plan = load_ros_map(path, settings.grid_resolution_m)
        else:
            raise PlanError(spec, f"unknown floor-plan kind {suffix or '(no suffix)'!r}: use procedural, a .svg, a .png "
                                  "or a ROS map_server .yaml")
    if settings.closed_doors or settings.closed_door_fraction > 0:
        plan.closed = close_doors(plan, settings.closed_door_fraction, settings.closed_doors, seed)
    if settings.waypoints:
        plan.paths = load_waypoints(Path(settings.waypoints), plan)
    return plan


def load_cubicasa_plan(path: Path) -> FloorPlan:
    """A CubiCasa5K ``model.svg`` as a FloorPlan: walls, railings and windows solid, doors cut out."""
    from swarmmap.shared.world.cubicasa import load_cubicasa

    cc = load_cubicasa(path)
    solid = [_polygon(p) for p in cc.walls + cc.railings + cc.windows]
    doors = [_polygon(p) for p in cc.doors]
    walls = unary_union(solid)
    if doors:
        walls = walls.difference(unary_union(doors))
    rooms = [_polygon(p) for _, p in cc.rooms]
    return FloorPlan(path.parent.name + "/" + path.name, str(path), walls, rooms, [name for name, _ in cc.rooms], doors,
                     kind="cubicasa")


def read_image(path: Path, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """An image's grey levels (uint8) and its alpha channel (None without one); a PlanError naming
    the file when it is unreadable, over MAX_IMAGE_BYTES, or larger than MAX_IMAGE_PIXELS, before
    its pixels are decoded. The file is read into memory first: a chunk whose stated length is
    wrong then reads what there is, and never makes PIL set aside the length it claims."""
    try:
        size = path.stat().st_size
        if size > MAX_IMAGE_BYTES:
            raise PlanError(path, f"file of {size} bytes is larger than {MAX_IMAGE_BYTES} (the largest image read)")
        with Image.open(io.BytesIO(path.read_bytes())) as img:
            if img.width * img.height > MAX_IMAGE_PIXELS:
                raise PlanError(path, f"image of {img.width} x {img.height} pixels is larger than {MAX_IMAGE_PIXELS}")
            alpha = np.asarray(img.getchannel("A")) if "A" in img.getbands() else None
            return np.asarray(img.convert("L")), alpha
    except PlanError:
        raise
    except Image.DecompressionBombError as exc:  # PIL refuses to open it at all: twice its own pixel limit
        words = str(exc).split("(", 1)[-1].split(")", 1)[0]
        raise PlanError(path, f"image larger than {MAX_IMAGE_PIXELS} pixels ({words})") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as exc:
        raise PlanError(path, f"not a readable {what}: {exc}") from None


def _polygon(points: np.ndarray) -> Polygon:
    poly = Polygon(points)
    return poly if poly.is_valid else poly.buffer(0)


def load_dinno_png(path: Path, pixels_per_metre: float, border_px: int, mesh_resolution: float) -> FloorPlan:
    """A DiNNO occupancy PNG as a raster FloorPlan (walls derived at ``mesh_resolution``)."""
    pixels, _ = read_image(path, "PNG image")
    occupied = pixels >= 128
    if border_px > 0:
        occupied[:border_px] = occupied[-border_px:] = True
        occupied[:, :border_px] = occupied[:, -border_px:] = True
    if occupied.all():
        raise PlanError(path, "the image has no free space (every pixel is occupied, value >= 128)")
    ny, nx = occupied.shape
    res = 1.0 / pixels_per_metre
    native = OccupancyGrid(occupied[::-1].astype(np.uint8), res, (-nx / 2 * res, -ny / 2 * res))
    coarse = native.resample(max(mesh_resolution, res))
    # One "room", the whole image: the planner may go anywhere free.
    return FloorPlan(path.name, str(path), grid_walls(coarse), [box(*coarse.bounds)], ["free space"], raster=native,
                     kind="dinno", image_size=(nx, ny))


ROS_MODES = ("trinary", "scale", "raw")


def load_ros_map(path: Path, mesh_resolution: float) -> FloorPlan:
    """A ROS ``map_server`` map: its ``.yaml`` (``image``, ``resolution``, ``origin``,
    ``occupied_thresh``, ``free_thresh``, ``negate``, ``mode``) and the image it names (relative
    to the YAML's folder), read as map_server reads it.

    Modes ``trinary`` and ``scale``: a pixel's occupancy is ``(255 - p) / 255`` (``p / 255`` with
    ``negate``); above ``occupied_thresh`` the cell is occupied, below ``free_thresh`` free, and in
    between unknown (``scale`` would make those cells probabilities; a ground truth has none).
    Mode ``raw``: the pixel is the occupancy in percent, and values above 100 are unknown. A
    transparent pixel is unknown, and so is a free pixel on the image's edge. Unknown cells are
    solid in the simulated world (robots do not drive there and the LiDAR stops at them) and
    never ground truth: the validation set and the scores leave them out. Image row 0 is the
    map's top; ``origin`` is the pose of its lower-left pixel (a rotated origin, yaw not 0, is
    refused)."""
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise PlanError(path, f"not a readable ROS map YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise PlanError(path, "a ROS map YAML must be a mapping with image, resolution and origin")
    missing = [k for k in ("image", "resolution", "origin") if k not in doc]
    if missing:
        raise PlanError(path, f"ROS map YAML lacks {', '.join(missing)}")
    mode = doc.get("mode", "trinary")
    if mode not in ROS_MODES:
        raise PlanError(path, f"unknown mode {mode!r}: map_server knows {', '.join(ROS_MODES)}")

    def number(key: str, default: float | None = None, lo: float = -math.inf, hi: float = math.inf) -> float:
        value = doc.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi or not math.isfinite(value):
            raise PlanError(path, f"{key} must be a number in [{lo}, {hi}], got {value!r}")
        return float(value)

    res = number("resolution", lo=1e-4, hi=100.0)
    occ_t, free_t = number("occupied_thresh", 0.65, 0.0, 1.0), number("free_thresh", 0.196, 0.0, 1.0)
    if free_t >= occ_t:
        raise PlanError(path, f"free_thresh {free_t} must be below occupied_thresh {occ_t}")
    negate = doc.get("negate", 0)
    if negate not in (0, 1, True, False):
        raise PlanError(path, f"negate must be 0 or 1, got {negate!r}")
    origin = doc["origin"]
    if (not isinstance(origin, list) or len(origin) not in (2, 3)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in origin)):
        raise PlanError(path, f"origin must be [x, y, yaw] in metres and radians, got {origin!r}")
    if len(origin) == 3 and abs(origin[2]) > 1e-9:
        raise PlanError(path, f"a rotated map (origin yaw {origin[2]}) is not supported: rotate the image instead")
    image = doc["image"]
    if not isinstance(image, str) or not image:
        raise PlanError(path, f"image must name the map's image file, got {image!r}")
    image_path = Path(image) if Path(image).is_absolute() else path.parent / image
    grey, alpha = read_image(image_path, "map image")
    pixels = grey.astype(np.float64)
    free, unknown = ros_cells(pixels, alpha, mode, bool(negate), occ_t, free_t)
    if not free.any():
        raise PlanError(path, f"the map has no free cell (occupancy below free_thresh {free_t}); check negate and the thresholds")
    ny, nx = free.shape
    native = OccupancyGrid((~free)[::-1].astype(np.uint8), res, (float(origin[0]), float(origin[1])),
                           unknown=unknown[::-1].copy())
    coarse = native.resample(max(mesh_resolution, res))
    return FloorPlan(path.name, str(path), grid_walls(coarse), [box(*coarse.bounds)], ["free space"], raster=native,
                     kind="rosmap", image_size=(nx, ny))


def ros_cells(pixels: np.ndarray, alpha: np.ndarray | None, mode: str, negate: bool, occ_t: float,
              free_t: float) -> tuple[np.ndarray, np.ndarray]:
    """(free, unknown) cells of a map_server image, row 0 = the image's top. The image's edge is
    never free: beyond it the world has no walls, so a free cell there (a learned map's, whose
    network guessed free space around the building) is taken as unknown, which keeps robots and
    LiDAR beams on the map."""
    if mode == "raw":
        unknown = pixels > 100
        occ = pixels / 100.0
    else:
        occ = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
        unknown = np.zeros(pixels.shape, dtype=bool)
    occupied = ~unknown & (occ > occ_t)
    free = ~unknown & (occ < free_t)
    if alpha is not None:  # a transparent pixel is unknown, whatever its value
        free &= alpha != 0
        occupied &= alpha != 0
    edge = np.zeros(free.shape, bool)
    edge[[0, -1], :] = edge[:, [0, -1]] = True
    free &= ~edge
    return free, ~(occupied | free)


def grid_walls(grid: OccupancyGrid):
    """Occupied cells of ``grid`` as polygons (runs of cells per row, merged)."""
    boxes = []
    res = grid.resolution
    ox, oy = grid.origin
    for r, row in enumerate(grid.grid > 0):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            boxes.append(box(ox + a * res, oy + r * res, ox + b * res, oy + (r + 1) * res))
    return unary_union(boxes).simplify(res * 0.01)


def load_waypoints(folder: Path, plan: FloorPlan) -> list[np.ndarray]:
    """Every ``*.npy`` in ``folder`` (sorted by the number in its name) as one robot's path."""
    from swarmmap.shared.world.paths import check_paths, interpolate_dinno

    if not folder.is_dir():
        raise PlanError(folder, missing(folder, "waypoint folder") if not folder.exists() else "not a folder")
    files = sorted(folder.glob("*.npy"), key=lambda f: (int(m.group()) if (m := re.search(r"\d+", f.stem)) else 1 << 30, f.name))
    if not files:
        raise PlanError(folder, "no .npy waypoint files in the folder")
    paths = []
    for f in files:
        try:
            arr = np.load(f, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise PlanError(f, f"not a readable .npy array: {exc}") from None
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 2 or not np.issubdtype(arr.dtype, np.number):
            raise PlanError(f, f"waypoints must be a numeric (K, 2) array with K >= 2, got {arr.dtype} {arr.shape}")
        arr = arr.astype(np.float64)
        if not np.isfinite(arr).all():
            raise PlanError(f, "waypoints hold NaN or infinite values")
        if plan.kind == "dinno" and plan.raster is not None and plan.image_size is not None:
            nx, ny = plan.image_size
            res = plan.raster.resolution
            if (np.abs(arr) > 1.0).any():
                raise PlanError(f, "DiNNO waypoints must lie in [-1, 1] (normalised image coordinates)")
            # DiNNO: pixels = w * (nx/2, ny/2) about the image centre, rows growing southwards.
            arr = interpolate_dinno(arr) * np.array([nx / 2 * res, -ny / 2 * res])
        try:
            check_paths([arr], plan.raster or plan.occupancy(0.05), f)
        except PlanError as exc:
            raise PlanError(f, exc.problem.replace("path 0: ", "")) from None
        paths.append(arr)
    return paths


MIN_PATH_M = 0.5  # a planned path shorter than this is a robot standing still


def robot_paths(cfg: RunConfig, plan: FloorPlan, grid: OccupancyGrid) -> list[np.ndarray]:
    """The plan's own waypoint paths (one per robot), or paths planned through free space; a
    plan with fewer waypoint paths than robots, or none a robot can drive, raises PlanError."""
    from swarmmap.shared.world.paths import path_length, plan_paths  # here: scipy only where paths are made

    if plan.paths is not None:
        if len(plan.paths) < cfg.robots:
            raise PlanError(cfg.world.waypoints, f"{len(plan.paths)} waypoint paths for {cfg.robots} robots: run at most "
                                                 f"{len(plan.paths)} robots (--robots), or give a folder with a path per robot")
        return plan.paths[: cfg.robots]
    paths = plan_paths(plan, grid, cfg.robots, cfg.seed, cfg.world.rooms_per_robot, cfg.world.robot_clearance_m,
                       cfg.world.coverage_spacing_m, cfg.world.rooms)
    lengths = [path_length(p) for p in paths]
    if max(lengths) < MIN_PATH_M:
        raise PlanError(plan.source, f"no usable path: the planned paths are {', '.join(f'{v:.1f}' for v in lengths)} m "
                                     f"(the plan has {len(plan.rooms)} room(s) a robot can reach); a robot that does not "
                                     "move sees one place only")
    still = [r for r, v in enumerate(lengths) if v < MIN_PATH_M]
    if still:
        log.warning("robot(s) %s have no path to drive (fewer reachable rooms than robots): each sees one place only", still)
    return paths
