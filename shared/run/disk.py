"""The disk a run directory lies on: whether it can be written, whether it is full, and its name
in messages (``the disk of runs/a: tmpfs mounted at /mnt/tiny, 0 B free of 200 kB``).

    problem = write_problem(run_dir)       # None, or why nothing can be written there
    if is_full(run_dir): print(disk_words(run_dir))
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

# Less than this free and a run cannot go on: one checkpoint of the smallest preset is larger.
FULL_BYTES = 1 << 20


def existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists."""
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def mount_of(path: Path) -> tuple[str, str]:
    """(mount point, filesystem type) of the disk holding ``path``, from /proc/mounts; ("", "")
    where that cannot be read (not Linux)."""
    real = os.path.realpath(existing(path))
    best = ("", "")
    try:
        lines = Path("/proc/mounts").read_text().splitlines()
    except OSError:
        return best
    for line in lines:
        parts = line.split()
        if len(parts) < 3:
            continue
        point = re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), parts[1])  # \040 is a space
        inside = real == point or real.startswith(point.rstrip("/") + "/")
        if inside and len(point) >= len(best[0]):
            best = (point, parts[2])
    return best


def free_bytes(path: Path) -> tuple[int, int]:
    """(bytes free to this user, bytes in all) on the disk holding ``path``."""
    usage = shutil.disk_usage(existing(path))
    return usage.free, usage.total


def size_words(n: float) -> str:
    """``0 B``, ``200 kB``, ``1.5 GB``."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit in ("B", "kB") else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


def disk_words(path: Path) -> str:
    """The disk of ``path`` in words: its filesystem, mount point and free space."""
    point, kind = mount_of(path)
    try:
        free, total = free_bytes(path)
        space = f"{size_words(free)} free of {size_words(total)}"
    except OSError as exc:
        space = f"its free space unknown ({exc.strerror})"
    where = f"{kind} mounted at {point}, " if point else ""
    return f"the disk of {path}: {where}{space}"


def is_full(path: Path) -> bool:
    """Whether the disk of ``path`` has less than FULL_BYTES free (False when that cannot be told)."""
    try:
        return free_bytes(path)[0] < FULL_BYTES
    except OSError:
        return False


def write_problem(path: Path) -> str | None:
    """Why nothing can be written in folder ``path`` (or, where it does not exist yet, in its
    nearest ancestor), or None: a file is really created and removed there, so that a read-only
    disk, missing permissions and a full disk are all found, for root too."""
    probe = existing(path)
    if not probe.is_dir():
        return f"{probe} is a file, not a folder"
    try:
        with tempfile.NamedTemporaryFile(dir=probe, prefix=".swarmmap-probe-") as f:
            f.write(b"x")
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        return f"{probe} cannot be written ({exc.strerror})"
    if is_full(probe):
        return f"{probe} lies on a full disk ({disk_words(probe).split(': ', 1)[1]})"
    return None
