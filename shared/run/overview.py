"""Pictures of learned maps on the viewer's scales, and a run's ``overview.png``.

The scales are the observer's: occupancy (ground truth and mean maps) on ``gray_r`` over 0..1
(white free, black occupied), the standard deviation on ``magma`` over 0..``observer.std_max``
(bright = uncertain), the error |mean - truth| on ``Reds`` over 0..1. ``overview.png`` (written by
the recorder once every learner has saved its maps, or by :func:`write_overview` for any run
directory) shows one row per robot: the ground truth with the robot's LiDAR hits, its mean map,
its std map where the model has one, and its error map, at the maps' own resolution (the
ground truth's), with axes in metres and a colour bar per scale. ``swarmmap experiment``'s map
figures draw with the same helpers.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("overview")

OCCUPANCY_CMAP, STD_CMAP, ERROR_CMAP = "gray_r", "magma", "Reds"
UNKNOWN_GREY = 0.5  # a ground-truth cell nobody knows (a ROS map's), on the occupancy scale
MAX_HITS_SHOWN = 4000  # LiDAR hits drawn per robot over the ground truth
Drives = tuple[np.ndarray, np.ndarray]  # a robot's driven path (K, 2) and its goals (G, 2), metres


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def colorize(values: np.ndarray, cmap: str, vmax: float) -> np.ndarray:
    """(H, W) values in [0, vmax] (row 0 = south) -> (H, W, 3) uint8 RGB, north up."""
    import matplotlib

    lut = (matplotlib.colormaps[cmap](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    idx = np.clip(np.nan_to_num(values / vmax) * 255, 0, 255).astype(np.uint8)
    return lut[np.flipud(idx)]


def map_extent(maps: dict[str, np.ndarray]) -> tuple[float, float, float, float]:
    """(left, right, bottom, top) in metres of a map's grid, for ``imshow(extent=...)``."""
    h, w = maps["mean"].shape
    res, (ox, oy) = float(maps["resolution"]), maps["origin"]
    return (ox, ox + w * res, oy, oy + h * res)


def robot_files(folder: Path, suffix: str) -> dict[int, Path]:
    """The ``robot-<i><suffix>`` files in ``folder``, by robot id in increasing order."""
    found = {}
    for p in folder.glob(f"robot-*{suffix}"):
        ident = p.name[len("robot-") : -len(suffix)]
        if ident.isdigit():  # (robot-0-std.png is no robot-<i>.png)
            found[int(ident)] = p
    return dict(sorted(found.items()))


def load_maps(run_dir: Path, robot: int) -> dict[str, np.ndarray]:
    """A robot's saved maps (``maps/robot-<i>.npz``: mean, std where its model has one, origin, resolution)."""
    path = run_dir / "maps" / f"robot-{robot}.npz"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no saved maps (the learner writes them when it finishes)")
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def truth_grid(run_dir: Path):
    """The run's ground-truth occupancy grid (``groundtruth.npz``: 0 free, 1 occupied, 2 unknown,
    never scored)."""
    from swarmmap.shared.world.grid import OccupancyGrid  # imported here: `swarmmap --help` stays quick

    with np.load(run_dir / "groundtruth.npz") as gt:
        return OccupancyGrid((gt["grid"] > 0).astype(np.uint8), float(gt["resolution"]), tuple(gt["origin"]),
                             unknown=gt["grid"] == 2)


def truth_on(grid, maps: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth on a map's cells: (occupied, known), both (H, W) bool."""
    shape = maps["mean"].shape
    fine = grid.resample(float(maps["resolution"]))
    truth = fine.grid[: shape[0], : shape[1]] > 0
    known = np.ones(shape, bool) if fine.unknown is None else ~fine.unknown[: shape[0], : shape[1]]
    return truth, known


def show(ax, values: np.ndarray, extent, kind: str, std_max: float = 0.25):
    """Draw a map of ``kind`` (occupancy, std or error) on its scale; returns the image (for a colour bar)."""
    cmap, vmax = {"occupancy": (OCCUPANCY_CMAP, 1.0), "std": (STD_CMAP, std_max), "error": (ERROR_CMAP, 1.0)}[kind]
    return ax.imshow(values, origin="lower", cmap=cmap, vmin=0, vmax=vmax, extent=extent, interpolation="nearest")


def error_map(maps: dict[str, np.ndarray], truth: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, str]:
    """|mean - truth| (NaN where the truth is unknown) and a caption with its mean and the
    mean map's accuracy (p > 0.5 against the truth) over the known cells."""
    err = np.where(known, np.abs(maps["mean"] - truth), np.nan)
    right = (maps["mean"] > 0.5) == truth
    return err, f"|mean - truth| {np.nanmean(err):.3f}, {100 * right[known].mean():.1f}% right"


def overview_figure(grid, maps: dict[int, dict[str, np.ndarray]], path: Path, std_max: float = 0.25,
                    notes: dict[int, str] | None = None, hits: dict[int, np.ndarray] | None = None,
                    truth: str = "ground truth", title: str = "", drives: dict[int, Drives] | None = None) -> None:
    """One row per robot (ground truth with its ``hits`` and, exploring, its ``drives``: the path it
    drove and its goals; mean, std where there is one, error), axes in metres, a colour bar per
    scale; written to ``path`` as a PNG, atomically. ``truth`` names what ``grid`` is (a run on a
    dataset: the log-odds grid, a reference)."""
    from swarmmap.shared.run.atomic import atomic_write_bytes

    plt = pyplot()
    robots = sorted(maps)
    with_std = any("std" in m for m in maps.values())
    kinds = ["truth", "mean"] + (["std"] if with_std else []) + ["error"]
    h, w = maps[robots[0]]["mean"].shape
    # A fixed layout (inches): constrained_layout would take most of the drawing time. Panels
    # grow with the map (up to 8 in at 200 dpi) so that a cell gets at least a pixel.
    panel, gap_x, gap_y, left, bottom, bar = float(np.clip(w / 200, 3.2, 8.0)), 0.75, 0.75, 1.0, 0.8, 0.45
    panel_h = panel * h / w
    width = left + len(kinds) * panel + (len(kinds) - 1) * gap_x + 0.3
    height = 0.5 + len(robots) * (panel_h + gap_y) + bar + bottom
    fig = plt.figure(figsize=(width, height))
    grid_spec = fig.add_gridspec(len(robots) + 1, len(kinds), height_ratios=[panel_h] * len(robots) + [bar * 0.35],
                                 left=left / width, right=1 - 0.3 / width, bottom=bottom / height, top=1 - 0.5 / height,
                                 wspace=gap_x / panel, hspace=gap_y / panel_h)
    axes = np.array([[fig.add_subplot(grid_spec[r, c]) for c in range(len(kinds))] for r in range(len(robots))])
    if title:
        fig.suptitle(title, y=1 - 0.12 / height, fontsize=10)
    images: dict[str, object] = {}
    for row, robot in zip(axes, robots):
        images |= overview_row(row, kinds, grid, maps[robot], std_max, (hits or {}).get(robot), robot, truth,
                               (drives or {}).get(robot))
        row[0].set_ylabel(f"robot {robot}" + (f"\n{notes[robot]}" if notes and robot in notes else "") + "\ny (m)")
    for ax in axes[-1]:
        ax.set_xlabel("x (m)")
    bars = {"mean": (f"occupancy ({truth}: unknown grey)", slice(0, 2)), "std": ("std of occupancy", slice(2, 3)),
            "error": ("|mean - truth|" if truth == "ground truth" else f"|mean - {truth}|", slice(len(kinds) - 1, len(kinds)))}
    for kind, (label, columns) in bars.items():
        if kind in images:
            fig.colorbar(images[kind], cax=fig.add_subplot(grid_spec[len(robots), columns]), orientation="horizontal",
                         label=label)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=max(100, min(200, int(np.ceil(w / panel)))))
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def overview_row(row, kinds: list[str], grid, maps: dict[str, np.ndarray], std_max: float, hits: np.ndarray | None,
                 robot: int, truth_name: str = "ground truth", drive: Drives | None = None) -> dict[str, object]:
    """One robot's panels of the overview; returns its images by kind."""
    import matplotlib

    ext = map_extent(maps)
    truth, known = truth_on(grid, maps)
    err, caption = error_map(maps, truth, known)
    if truth_name != "ground truth":
        caption = caption.replace("truth", truth_name.split(" (")[0]).replace("right", "agree")
    images = {}
    for ax, kind in zip(row, kinds):
        if kind == "truth":
            show(ax, np.where(known, truth.astype(float), UNKNOWN_GREY), ext, "occupancy")
            if hits is not None and len(hits):
                ax.scatter(hits[:, 0], hits[:, 1], s=0.3, color=matplotlib.colormaps["tab10"](robot % 10), linewidths=0)
            ax.set_title(f"{truth_name}, its LiDAR hits" if hits is not None and len(hits) else truth_name, fontsize=9, y=1.0)
            if drive is not None:
                driven, goals = drive
                ax.plot(driven[:, 0], driven[:, 1], color="tab:red", linewidth=0.8)
                ax.scatter(goals[:, 0], goals[:, 1], marker="x", s=12, color="tab:red", linewidths=0.8)
                ax.set_title(f"{truth_name}, its hits, drive (line) and goals (x)", fontsize=9, y=1.0)
        elif kind == "mean":
            images["mean"] = show(ax, maps["mean"], ext, "occupancy")
            ax.set_title("mean occupancy", fontsize=9, y=1.0)
        elif kind == "std":
            if "std" in maps:
                images["std"] = show(ax, maps["std"], ext, "std", std_max)
            ax.set_title("standard deviation" if "std" in maps else "no std (deterministic model)", fontsize=9, y=1.0)
        else:
            images["error"] = show(ax, err, ext, "error")
            ax.set_title(caption, fontsize=9, y=1.0)
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.tick_params(labelsize=7)
    return images


def robot_hits(run_dir: Path, robot: int, limit: int = MAX_HITS_SHOWN) -> np.ndarray | None:
    """Up to ``limit`` of a robot's occupied training points (its LiDAR hits), evenly picked."""
    path = run_dir / "data" / f"robot-{robot}.npz"
    if not path.exists():
        return None
    with np.load(path) as z:
        hits = z["points"][z["labels"] > 0.5]
    return hits[:: max(1, len(hits) // limit)]


def robot_drives(run_dir: Path) -> dict[int, Drives]:
    """Exploring runs: each robot's driven path (``exploration.csv``) and goals (``goals.csv``)."""
    if not (run_dir / "exploration.csv").exists():
        return {}
    from swarmmap.shared.world.explore import GOAL_COLUMNS, read_exploration

    try:
        rows = read_exploration(run_dir / "exploration.csv")
        goals = read_exploration(run_dir / "goals.csv", GOAL_COLUMNS) if (run_dir / "goals.csv").exists() else []
    except (OSError, ValueError) as exc:
        log.warning("no drives in overview.png: %s", exc)
        return {}
    out = {}
    for r in sorted({int(row["robot"]) for row in rows}):
        out[r] = (np.array([(row["x"], row["y"]) for row in rows if row["robot"] == r]).reshape(-1, 2),
                  np.array([(g["x"], g["y"]) for g in goals if g["robot"] == r and not g["done"]]).reshape(-1, 2))
    return out


def write_overview(run_dir: Path, std_max: float = 0.25, notes: dict[int, str] | None = None) -> Path | None:
    """``run_dir/overview.png`` from the run's ground truth and every ``maps/robot-<i>.npz``;
    returns its path, or None (saying why) when the run has no ground truth or no maps yet."""
    if not (run_dir / "groundtruth.npz").exists():
        log.warning("no overview.png: %s is missing", run_dir / "groundtruth.npz")
        return None
    robots = robot_files(run_dir / "maps", ".npz")
    if not robots:
        log.warning("no overview.png: %s holds no robot-<i>.npz", run_dir / "maps")
        return None
    maps = {r: load_maps(run_dir, r) for r in robots}
    path = run_dir / "overview.png"
    with np.load(run_dir / "groundtruth.npz") as gt:
        truth = "log-odds grid (reference)" if "reference" in gt.files else "ground truth"
    from swarmmap.shared.run.rundir import config_doc, run_words

    title = f"run {config_doc(run_dir).get('run_id', run_dir.name)}: {run_words(run_dir)}"
    overview_figure(truth_grid(run_dir), maps, path, std_max, notes, {r: robot_hits(run_dir, r) for r in robots}, truth, title,
                    robot_drives(run_dir))
    return path
