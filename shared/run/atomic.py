"""Files that are whole or absent: write to a temporary sibling, fsync, rename."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_write_bytes(path: Path | str, data: bytes, mode: int | None = None) -> None:
    """Replace ``path`` with ``data`` so that a crash leaves either the old or the new file; the
    file has ``mode`` from its first byte (default: the usual mode under the umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK if mode is None else mode)  # mkstemp makes 0600
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path | str, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def save_png(path: Path | str, occupancy: np.ndarray, resolution: float | None = None) -> None:
    """Write an occupancy-probability grid (H, W) in [0, 1], row 0 = south, as an 8-bit PNG:
    dark = occupied, white = free, north up; with its ``resolution`` (m a cell), a scale bar."""
    import io

    from PIL import Image

    img = Image.fromarray((255 * (1 - np.clip(occupancy, 0, 1)))[::-1].round().astype(np.uint8))
    if resolution is not None:
        scale_bar(img, resolution)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())


BAR_METRES = (0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)


def scale_bar(img, resolution: float) -> None:
    """Draw a scale bar into a map image (PIL, one pixel a cell of ``resolution`` m) in its
    lower-left corner: the longest round length of at most a quarter of its width, with its length
    written over it, on a white box so that it reads on any map."""
    from PIL import ImageDraw

    metres = max((m for m in BAR_METRES if m / resolution <= img.width / 4), default=None)
    if metres is None or img.height < 24:
        return
    n = int(round(metres / resolution))
    words = f"{metres:g} m"
    draw = ImageDraw.Draw(img)
    black, white = (0, 0, 0) if img.mode == "RGB" else 0, (255, 255, 255) if img.mode == "RGB" else 255
    x0, y1 = 4, img.height - 4
    draw.rectangle([x0 - 2, y1 - 20, x0 + max(n, 6 * len(words)) + 2, y1 + 2], fill=white)
    draw.rectangle([x0, y1 - 3, x0 + n, y1], fill=black)
    draw.text((x0, y1 - 17), words, fill=black)
