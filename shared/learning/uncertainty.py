"""How good a map's uncertainty is: scores of a mean map and a std map against the ground truth.

Beyond the paper (which shows its std maps as pictures), every score here answers a question a
user asks of an uncertainty map:

- ``nll``: the negative log-likelihood (binary cross-entropy) of the true occupancy under the
  mean map, per cell. Lower is better.
- ``ece``: expected calibration error of the mean map (10 equal-width bins of the predicted
  occupancy; the cell-weighted gap between the bin's mean prediction and its true frequency);
  ``reliability`` holds those bins, for a reliability diagram.
- ``auroc_error``: how well the std ranks the cells where the map is wrong (mean on the wrong
  side of 0.5) above the cells where it is right: 1 is perfect, 0.5 is no better than chance.
- ``auroc_unobserved``: how well the std ranks the cells no robot saw above the cells they saw:
  the question of the paper ("is the std high where nobody looked?"), 1 perfect, 0.5 chance.
- ``std_observed`` / ``std_unobserved``: mean std over cells within ``radius`` of a training
  point (the robots saw them) and over the cells no robot saw, with ``std_ratio`` =
  unobserved / observed: above 1 means the map is more uncertain where it has no data.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage, stats

from swarmmap.shared.world.grid import OccupancyGrid


def observed_mask(shape: tuple[int, int], origin: tuple[float, float], resolution: float, points: np.ndarray,
                  radius_m: float = 0.1) -> np.ndarray:
    """Cells (H, W) of a map grid within ``radius_m`` of at least one of ``points`` (N, 2)."""
    grid = OccupancyGrid(np.zeros(shape, np.uint8), resolution, (float(origin[0]), float(origin[1])))
    seen = np.zeros(shape, bool)
    if len(points):
        rows, cols, inside = grid.cells(np.asarray(points))
        seen[rows[inside], cols[inside]] = True
    steps = int(math.floor(radius_m / resolution))
    return ndimage.binary_dilation(seen, iterations=steps) if steps > 0 and seen.any() else seen


def auroc(scores: np.ndarray, positives: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` for finding ``positives`` (the Mann-Whitney U
    statistic, ties counting half); NaN when either class is empty."""
    scores, positives = np.asarray(scores, np.float64).ravel(), np.asarray(positives, bool).ravel()
    n_pos, n_neg = int(positives.sum()), int((~positives).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = stats.rankdata(scores)  # average ranks of ties
    return float((ranks[positives].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def reliability(mean: np.ndarray, truth: np.ndarray, bins: int = 10) -> dict[str, list]:
    """The reliability diagram of predicted occupancies ``mean`` against 0/1 ``truth``: per
    equal-width bin of the prediction, the mean prediction, the true frequency of occupied
    cells and the number of cells (None for an empty bin: JSON-ready)."""
    mean, truth = np.asarray(mean, np.float64).ravel(), np.asarray(truth, np.float64).ravel()
    which = np.clip((mean * bins).astype(int), 0, bins - 1)
    out: dict[str, list] = {"predicted": [], "frequency": [], "cells": []}
    for b in range(bins):
        sel = which == b
        n = int(sel.sum())
        out["predicted"].append(float(mean[sel].mean()) if n else None)
        out["frequency"].append(float(truth[sel].mean()) if n else None)
        out["cells"].append(n)
    return out


def calibration_error(mean: np.ndarray, truth: np.ndarray, bins: int = 10) -> float:
    """Expected calibration error of predicted occupancies ``mean`` against 0/1 ``truth``: the
    cell-weighted gap between prediction and frequency over :func:`reliability`'s bins."""
    rel = reliability(mean, truth, bins)
    total = sum(n * abs(p - f) for p, f, n in zip(rel["predicted"], rel["frequency"], rel["cells"]) if n)
    return float(total / max(sum(rel["cells"]), 1))


def score_map(mean: np.ndarray, std: np.ndarray, truth: np.ndarray, observed: np.ndarray) -> dict:
    """Every score of the module docstring for one map (floats), and its ``reliability``
    diagram; arrays share a shape, ``truth`` 0/1."""
    mean = np.clip(np.asarray(mean, np.float64), 1e-6, 1 - 1e-6)
    truth = np.asarray(truth, bool)
    observed = np.asarray(observed, bool)
    nll = -(truth * np.log(mean) + (~truth) * np.log(1 - mean))
    wrong = (mean >= 0.5) != truth
    s_obs = float(std[observed].mean()) if observed.any() else float("nan")
    s_un = float(std[~observed].mean()) if (~observed).any() else float("nan")
    return {"nll": float(nll.mean()), "ece": calibration_error(mean, truth), "accuracy": float(1 - wrong.mean()),
            "auroc_error": auroc(std, wrong), "auroc_unobserved": auroc(std, ~observed),
            "std_observed": s_obs, "std_unobserved": s_un,
            "std_ratio": s_un / s_obs if s_obs > 0 else float("nan"), "observed_fraction": float(observed.mean()),
            "reliability": reliability(mean, truth)}
