"""LiDAR geometry shared by the world, the lidar streamers and the validation set.

:func:`beam_samples` turns one scan into DiNNO-style labelled points: free samples at fixed
spacing along each beam (``samples_per_beam`` over the full range, as DiNNO's ``Lidar2D``
does), cut at the hit, plus the hit point pushed ``occupied_depth`` into the surface and
labelled occupied. :func:`raycast_grid` casts beams in a ground-truth occupancy grid.
"""

from __future__ import annotations

import numpy as np

from swarmmap.shared.floorplan import OccupancyGrid


def beam_angles(beams: int, fov_deg: float = 360.0) -> np.ndarray:
    """Beam angles relative to the heading: ``beams`` over [-fov/2, fov/2), float32."""
    half = np.deg2rad(fov_deg) / 2
    return np.linspace(-half, half, beams, endpoint=not np.isclose(fov_deg, 360.0)).astype(np.float32)


def beam_samples(position: np.ndarray, angles: np.ndarray, ranges: np.ndarray, hit: np.ndarray,
                 max_range: float, samples_per_beam: int, occupied_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Labelled points (M, 2) float32 and labels (M,) float32 (0 free, 1 occupied) of one scan.

    ``angles`` are absolute (world frame) beam directions; ``hit[i]`` false means beam i saw
    nothing within ``max_range`` (all its samples are free).
    """
    position = np.asarray(position, dtype=np.float64).reshape(1, 2)
    angles = np.asarray(angles, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    hit = np.asarray(hit, dtype=bool)
    dirs = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (B, 2)
    t = np.linspace(0.0, max_range, samples_per_beam) if samples_per_beam > 1 else np.zeros(1)
    # Free up to the hit; a beam with no return is free over its whole length.
    keep = (t[None, :] < ranges[:, None]) | (~hit[:, None] & (t[None, :] <= ranges[:, None]))  # (B, S)
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
    """DiNNO's validation data: beams from random free poses, labelled from the ground truth."""
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
    return points, labels_all
