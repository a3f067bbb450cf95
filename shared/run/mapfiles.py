"""A map's files: ROS ``map_server`` maps (``.yaml`` + ``.pgm``) and a learned map's arrays and pictures.

A learned map is a dict of arrays on a regular grid, row 0 = south: ``mean`` (occupancy
probability), ``std`` where the model has one (BNN, MC dropout), ``origin`` (x, y of the grid's
lower-left corner, metres) and ``resolution`` (metres a cell). :func:`save_learned_map` writes
it as ``NAME.npz``, ``NAME-mean.png`` and ``NAME-std.png`` on the viewer's scales, and as a ROS
map: ``NAME.yaml`` + ``NAME.pgm`` (trinary with map_server's standard thresholds: the mean above
``occupied_thresh`` is occupied, below ``free_thresh`` free, in between unknown), which
``swarmmap up --floorplan NAME.yaml`` loads back as a plan, and the std as ``NAME-std.yaml`` +
``NAME-std.pgm`` (mode scale, thresholds 0 and 1: a pixel ``p`` stands for std
``std_max * (255 - p) / 255``, and map_server's occupancy grows linearly with the std).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import yaml

from swarmmap.shared.run.atomic import atomic_write_bytes, save_png, scale_bar
from swarmmap.shared.run.overview import STD_CMAP, colorize

# map_server's standard thresholds and the pixels map_saver writes in trinary mode.
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
OCCUPIED_PIXEL, FREE_PIXEL, UNKNOWN_PIXEL = 0, 254, 205


def pgm_bytes(pixels: np.ndarray, comment: str = "") -> bytes:
    """An 8-bit binary PGM (P5) of ``pixels`` (H, W, row 0 = the image's top) with ``comment``
    lines in its header (map_server and PIL skip them)."""
    h, w = pixels.shape
    notes = "".join(f"# {line}\n" for line in comment.splitlines())
    return f"P5\n{notes}{w} {h}\n255\n".encode() + np.ascontiguousarray(pixels, np.uint8).tobytes()


def save_ros_map(yaml_path: Path, pixels: np.ndarray, resolution: float, origin: tuple[float, float], comment: str = "",
                  mode: str = "trinary", occupied_thresh: float = OCCUPIED_THRESH, free_thresh: float = FREE_THRESH) -> None:
    """A ROS map_server map: ``yaml_path`` and the PGM beside it (same name, ``.pgm``) of
    ``pixels`` (H, W uint8, row 0 = south: the image is written north up, ``origin`` is its
    lower-left corner). ``comment`` heads both files."""
    image = yaml_path.with_suffix(".pgm")
    atomic_write_bytes(image, pgm_bytes(pixels[::-1], comment))
    doc = {"image": image.name, "resolution": float(resolution), "origin": [float(origin[0]), float(origin[1]), 0.0],
           "negate": 0, "occupied_thresh": float(occupied_thresh), "free_thresh": float(free_thresh), "mode": mode}
    notes = "".join(f"# {line}\n" for line in comment.splitlines())
    atomic_write_bytes(yaml_path, (notes + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)).encode())


def trinary_pixels(occupied: np.ndarray, unknown: np.ndarray | None = None) -> np.ndarray:
    """map_saver's trinary pixels of a grid: 0 occupied, 254 free, 205 unknown."""
    pixels = np.where(occupied, OCCUPIED_PIXEL, FREE_PIXEL).astype(np.uint8)
    if unknown is not None:
        pixels[unknown] = UNKNOWN_PIXEL
    return pixels


def occupancy_pixels(mean: np.ndarray) -> np.ndarray:
    """Trinary pixels of an occupancy-probability map under the standard thresholds."""
    occupied, free = mean > OCCUPIED_THRESH, mean < FREE_THRESH
    return trinary_pixels(occupied, ~(occupied | free))


def std_pixels(std: np.ndarray, std_max: float) -> np.ndarray:
    """A std map as map_server ``scale`` pixels: 255 for 0, 0 for ``std_max`` and above."""
    return (255 * (1 - np.clip(np.nan_to_num(std) / std_max, 0, 1))).round().astype(np.uint8)


def save_learned_map(folder: Path, name: str, maps: dict[str, np.ndarray], std_max: float) -> list[Path]:
    """Write a learned map's arrays, PNGs and ROS maps (see the module's docstring) into
    ``folder``, each file atomically; returns the paths written."""
    res, origin = float(maps["resolution"]), tuple(float(v) for v in maps["origin"])
    buf = io.BytesIO()
    np.savez_compressed(buf, **maps)
    written = [folder / f"{name}.npz", folder / f"{name}-mean.png", folder / f"{name}.yaml", folder / f"{name}.pgm"]
    atomic_write_bytes(written[0], buf.getvalue())
    save_png(written[1], maps["mean"], res)
    save_ros_map(written[2], occupancy_pixels(maps["mean"]), res, origin,
                  f"swarmmap learned map {name}: mean occupancy, occupied above {OCCUPIED_THRESH}, free below "
                  f"{FREE_THRESH}, unknown in between")
    if "std" in maps:
        from PIL import Image

        img, picture = io.BytesIO(), Image.fromarray(colorize(maps["std"], STD_CMAP, std_max))
        scale_bar(picture, res)
        picture.save(img, format="PNG")
        written += [folder / f"{name}-std.png", folder / f"{name}-std.yaml", folder / f"{name}-std.pgm"]
        atomic_write_bytes(written[-3], img.getvalue())
        save_ros_map(written[-2], std_pixels(maps["std"], std_max), res, origin,
                      f"swarmmap learned map {name}: std of occupancy = {std_max:g} * (255 - pixel) / 255 "
                      "(mode scale: map_server's occupancy grows linearly with the std)",
                      mode="scale", occupied_thresh=1.0, free_thresh=0.0)
    return written
