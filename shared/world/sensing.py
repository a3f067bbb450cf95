"""LiDAR geometry shared by the world, the lidar streamers and the validation set.

:func:`beam_samples` turns one scan into DiNNO-style labelled points: free samples at fixed
spacing along each beam (``samples_per_beam`` over the full range, as DiNNO's ``Lidar2D``
does), cut at the hit, plus the hit point pushed ``occupied_depth`` into the surface and
labelled occupied. :func:`raycast_grid` casts beams in a ground-truth occupancy grid.
"""

from __future__ import annotations

import numpy as np

from swarmmap.shared.wire.protocol import ValidationRecipe, WorldMap
from swarmmap.shared.world.grid import OccupancyGrid


def beam_angles(beams: int, fov_deg: float = 360.0) -> np.ndarray:
    """Beam angles relative to the heading: ``beams`` over [-fov/2, fov/2), float32."""
    half = np.deg2rad(fov_deg) / 2
    return np.linspace(-half, half, beams, endpoint=not np.isclose(fov_deg, 360.0)).astype(np.float32)


def along_beams(position, angles: np.ndarray, ranges: np.ndarray, step: float, through_end: bool = False) -> np.ndarray:
    """Points (M, 2) every ``step`` along each beam from ``position`` (``angles`` absolute): those
    before the beam's end (``ranges``), or with ``through_end`` up to a step past it (the cell it ended in)."""
    ranges = np.asarray(ranges)
    t = np.arange(0.0, float(np.max(ranges, initial=0.0)) + step, step)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    pts = np.asarray(position[:2], np.float64)[None, None, :] + t[None, :, None] * d[:, None, :]  # (B, T, 2)
    keep = t[None, :] <= ranges[:, None] + step if through_end else t[None, :] < ranges[:, None]
    return pts[keep]


def beam_ends(position, angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """The returns of one scan from ``position`` (x, y, ...) as points (K, 2): the ends of the beams that ``hit``."""
    a, r = np.asarray(angles)[hit], np.asarray(ranges)[hit]
    return np.stack([position[0] + r * np.cos(a), position[1] + r * np.sin(a)], axis=1)


def sensor_model(ranges: np.ndarray, hit: np.ndarray, rng: np.random.Generator, *, noise_std: float,
                 dropout_prob: float, min_range: float, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A real sensor's view of ideal ranges: Gaussian range noise on returns, dropouts (no
    return at all), and returns pushed past ``max_range`` becoming max-range returns (no hit).
    Returns (ranges, hit, valid): ``valid`` false marks a dropped beam."""
    ranges = np.asarray(ranges, dtype=np.float64).copy()
    hit = np.asarray(hit, dtype=bool).copy()
    if noise_std > 0:
        ranges[hit] += rng.normal(0.0, noise_std, size=int(hit.sum()))
    valid = rng.uniform(size=ranges.shape) >= dropout_prob if dropout_prob > 0 else np.ones(ranges.shape, bool)
    beyond = hit & (ranges >= max_range)
    hit &= ~beyond
    ranges = np.clip(np.where(hit, ranges, max_range), min_range, max_range)
    return ranges, hit, valid


def beam_samples(position: np.ndarray, angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray,
                 max_range: float, samples_per_beam: int, occupied_depth: float, *, sampling: str = "fixed",
                 rng: np.random.Generator | None = None, free_on_max_range: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Labelled points (M, 2) float32 and labels (M,) float32 (0 free, 1 occupied) of one scan.

    ``angles`` are absolute (world frame) beam directions; ``hit[i]`` false means beam i saw
    nothing within ``max_range`` (all its samples are free, unless ``free_on_max_range`` is
    off). ``sampling`` "fixed" puts the free samples at DiNNO's fixed spacing over the full
    range; "uniform" draws them uniformly up to the hit (needs ``rng``).
    """
    if sampling == "uniform":
        if rng is None:
            raise ValueError("uniform sampling needs an rng")
        ranges_ = np.asarray(ranges, dtype=np.float64)
        hit_ = np.asarray(hit, dtype=bool)
        keep_beam = hit_ | free_on_max_range
        t = rng.uniform(0.0, 1.0, size=(len(ranges_), samples_per_beam)) * ranges_[:, None]
        angles_ = np.asarray(angles, dtype=np.float64)
        dirs = np.stack([np.cos(angles_), np.sin(angles_)], axis=1)
        pos = np.asarray(position, dtype=np.float64).reshape(1, 2)
        free_pts = (pos[:, None, :] + t[:, :, None] * dirs[:, None, :])[keep_beam].reshape(-1, 2)
        occ_pts = pos + (ranges_[hit_] + occupied_depth)[:, None] * dirs[hit_]
        points = np.concatenate([free_pts, occ_pts]).astype(np.float32)
        labels = np.concatenate([np.zeros(len(free_pts)), np.ones(len(occ_pts))]).astype(np.float32)
        return points, labels
    position = np.asarray(position, dtype=np.float64).reshape(1, 2)
    angles = np.asarray(angles, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    hit = np.asarray(hit, dtype=bool)
    dirs = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (B, 2)
    t = np.linspace(0.0, max_range, samples_per_beam) if samples_per_beam > 1 else np.zeros(1)
    # Free up to the hit; a beam with no return is free over its whole length.
    keep = (t[None, :] < ranges[:, None]) | (~hit[:, None] & (t[None, :] <= ranges[:, None]))  # (B, S)
    if not free_on_max_range:
        keep &= hit[:, None]
    free = position[:, None, :] + t[None, :, None] * dirs[:, None, :]  # (B, S, 2)
    free_pts = free[keep]
    occ_pts = position + (ranges[hit] + occupied_depth)[:, None] * dirs[hit]
    points = np.concatenate([free_pts, occ_pts]).astype(np.float32)
    labels = np.concatenate([np.zeros(len(free_pts)), np.ones(len(occ_pts))]).astype(np.float32)
    return points, labels


def raycast_grid(grid: OccupancyGrid, origins: np.ndarray, angles: np.ndarray, max_range: float,
                 chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Ranges (N, B) and hit mask (N, B) of beams from ``origins`` (N, 2) along absolute
    ``angles`` (N, B) in ``grid``, marched at a quarter cell."""
    origins = np.asarray(origins, dtype=np.float64)
    angles = np.broadcast_to(np.asarray(angles, dtype=np.float64), (len(origins), np.shape(angles)[-1]))
    step = grid.resolution / 4
    t = np.arange(step, max_range + step, step)
    ranges = np.full(angles.shape, max_range, dtype=np.float64)
    hits = np.zeros(angles.shape, dtype=bool)
    for s in range(0, len(origins), chunk):
        o = origins[s : s + chunk]
        a = angles[s : s + chunk]
        d = np.stack([np.cos(a), np.sin(a)], axis=-1)  # (n, B, 2)
        pts = o[:, None, None, :] + t[None, None, :, None] * d[:, :, None, :]  # (n, B, T, 2)
        occ = grid.occupied(pts)
        first = occ.argmax(axis=2)
        any_hit = occ.any(axis=2)
        r = np.where(any_hit, t[first], max_range)
        ranges[s : s + chunk] = np.minimum(r, max_range)
        hits[s : s + chunk] = any_hit & (t[first] <= max_range)
    return ranges, hits


def validation_set(grid: OccupancyGrid, scans: int, beams: int, max_range: float, samples_per_beam: int,
                   seed: int, occupied_depth: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """DiNNO's validation data: beams from random free poses, labelled from the ground truth
    (samples in the grid's unknown cells, where it has any, left out)."""
    rng = np.random.default_rng(seed + 104729)
    poses = grid.random_free(scans, rng, clearance=0.15)
    angles = rng.uniform(-np.pi, np.pi, size=(scans, 1)) + beam_angles(beams)[None, :]
    ranges, hits = raycast_grid(grid, poses, angles, max_range)
    pts, labels = [], []
    for i in range(scans):
        p, lab = beam_samples(poses[i], angles[i], ranges[i], hits[i], max_range, samples_per_beam, occupied_depth)
        pts.append(p)
        labels.append(lab)
    points = np.concatenate(pts)
    labels_all = np.concatenate(labels)
    # Labels come from the grid itself, so a sample never disagrees with the ground truth.
    labels_all = grid.occupied(points).astype(np.float32)
    if grid.unknown is not None:  # a cell nobody knows is no ground truth
        rows, cols, _ = grid.cells(points)
        known = ~grid.unknown[rows, cols]
        points, labels_all = points[known], labels_all[known]
    return points, labels_all


def validation_recipe(grid: OccupancyGrid, scans: int, beams: int, max_range: float, samples_per_beam: int,
                      seed: int, occupied_depth: float = 0.03) -> ValidationRecipe:
    """The :class:`~swarmmap.shared.wire.protocol.ValidationRecipe` of :func:`validation_set` with
    these arguments, with the figures of its draw on ``grid`` that a receiver checks its own by."""
    points, labels = validation_set(grid, scans, beams, max_range, samples_per_beam, seed, occupied_depth)
    centre = points.astype(np.float64).mean(axis=0) if len(points) else np.zeros(2)
    return ValidationRecipe(scans=scans, beams=beams, max_range=max_range, samples_per_beam=samples_per_beam,
                            seed=seed, occupied_depth=occupied_depth, count=len(points),
                            occupied=int(labels.sum()), centroid=[float(c) for c in centre])


def draw_validation(world: WorldMap) -> tuple[np.ndarray, np.ndarray, str | None]:
    """``world``'s validation set (points, labels) drawn from its grid by its recipe, and what
    sets it apart from the world's own draw (None when it agrees: the same count and labels to
    within a point in ten thousand, the mean within a millimetre: floating point on another
    CPU may move a point by a bit, another numpy may draw another set)."""
    r = world.validation
    if r is None:
        raise ValueError("the world sent its validation points; nothing to draw")
    raw = world.grid.numpy()
    unknown = raw == 2
    grid = OccupancyGrid((raw != 0).astype(np.uint8), world.resolution, (world.origin[0], world.origin[1]),
                         unknown=unknown if unknown.any() else None)
    points, labels = validation_set(grid, r.scans, r.beams, r.max_range, r.samples_per_beam, r.seed, r.occupied_depth)
    slack = 1 + r.count // 10_000
    centre = points.astype(np.float64).mean(axis=0) if len(points) else np.zeros(2)
    if abs(len(points) - r.count) > slack or abs(int(labels.sum()) - r.occupied) > slack:
        return points, labels, (f"{len(points)} points ({int(labels.sum())} occupied) where the world drew "
                                f"{r.count} ({r.occupied} occupied)")
    if np.abs(centre - np.asarray(r.centroid)).max() > 1e-3:
        return points, labels, (f"their mean at ({centre[0]:.4f}, {centre[1]:.4f}) where the world's is at "
                                f"({r.centroid[0]:.4f}, {r.centroid[1]:.4f})")
    return points, labels, None
