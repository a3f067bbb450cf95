"""LiDAR recordings: the training-point stream a lidar streamer served, in a self-describing file.

Layout (all integers little-endian)::

    b"SWMREC01"                                   magic and format version
    frame*: u32 length, u32 CRC-32 of body, body   body = one msgpack map
      frame 0      {"kind": "header", "v": 1, "robot", "created", "config", "plan"}
      frames 1..n  {"kind": "samples", "t": seconds since the first, "payload": the Samples message bytes}
      frame n+1    {"kind": "footer", "frames": n, "sha256": hex digest of every payload in order}

``config`` is the recording run's resolved RunConfig (sensor, world and seed included) and
``plan`` names its floor plan (file path and SHA-256). The writer writes ``FILE.partial`` and
renames it to ``FILE`` only after the footer is on disk, so a crash never leaves a truncated
file that looks whole; whatever complete frames a crash left in ``FILE.partial`` can still be
read with ``allow_incomplete``. The reader checks every CRC, the order of the frames and the
footer's count and digest, and names the file and the problem when anything is off.
"""

from __future__ import annotations

import hashlib
import os
import struct
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from swarmmap.shared.wire.codec import Bounds, unpack_bounded

MAGIC = b"SWMREC01"
VERSION = 1
_FRAME = struct.Struct("<II")
MAX_FRAME_BYTES = 64 * 1024 * 1024
FRAME_BOUNDS = Bounds(MAX_FRAME_BYTES, containers=10_000, items=100_000, entries=1024)  # a header's config at most


class RecordingError(ValueError):
    """A recording that cannot be used; the message names the file and the problem."""

    def __init__(self, path: object, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


class RecordingWriter:
    """Appends frames to ``FILE.partial``; :meth:`close` adds the footer and renames to ``FILE``."""

    def __init__(self, path: Path, robot: int, config: dict[str, Any], plan: dict[str, Any], fsync_every: float = 2.0):
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.partial.open("wb")
        self._file.write(MAGIC)
        self._digest = hashlib.sha256()
        self._count = 0
        self._t0: float | None = None
        self._fsync_every = fsync_every
        self._last_sync = time.monotonic()
        self._frame({"kind": "header", "v": VERSION, "robot": robot, "created": time.time(), "config": config, "plan": plan})

    def _frame(self, doc: dict[str, Any]) -> None:
        body = msgpack.packb(doc, use_bin_type=True)
        self._file.write(_FRAME.pack(len(body), zlib.crc32(body)) + body)
        self._file.flush()
        if time.monotonic() - self._last_sync > self._fsync_every:
            os.fsync(self._file.fileno())
            self._last_sync = time.monotonic()

    def add(self, payload: bytes) -> None:
        """Append one Samples message (its wire bytes)."""
        now = time.monotonic()
        self._t0 = now if self._t0 is None else self._t0
        self._digest.update(payload)
        self._count += 1
        self._frame({"kind": "samples", "t": now - self._t0, "payload": payload})

    def close(self) -> Path:
        """Write the footer, fsync, and rename the file into place."""
        self._frame({"kind": "footer", "frames": self._count, "sha256": self._digest.hexdigest()})
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(self.partial, self.path)
        return self.path

    def abandon(self) -> None:
        """Close without a footer: the ``.partial`` file stays, marked incomplete."""
        self._file.close()


@dataclass
class Recording:
    """A recording read back: its header and its frames (time offset, Samples bytes)."""

    path: Path
    header: dict[str, Any]
    frames: list[tuple[float, bytes]]
    complete: bool

    @property
    def robot(self) -> int:
        return int(self.header["robot"])

    @property
    def config(self) -> dict[str, Any]:
        return self.header["config"]


def _frames(path: Path, data: bytes) -> Iterator[dict[str, Any]]:
    pos = len(MAGIC)
    index = 0
    while pos < len(data):
        if pos + _FRAME.size > len(data):
            raise RecordingError(path, f"truncated: frame {index} header cut off at byte {pos}")
        length, crc = _FRAME.unpack_from(data, pos)
        pos += _FRAME.size
        if length > MAX_FRAME_BYTES:
            raise RecordingError(path, f"frame {index} claims {length} bytes (over {MAX_FRAME_BYTES}): corrupt")
        if pos + length > len(data):
            raise RecordingError(path, f"truncated: frame {index} needs {length} bytes, {len(data) - pos} remain")
        body = data[pos : pos + length]
        pos += length
        if zlib.crc32(body) != crc:
            raise RecordingError(path, f"checksum mismatch in frame {index}: the file is corrupt")
        try:
            doc = unpack_bounded(body, FRAME_BOUNDS, MAX_FRAME_BYTES)
        except Exception as exc:  # msgpack raises several unrelated types
            raise RecordingError(path, f"frame {index} is not msgpack: {exc}") from None
        if not isinstance(doc, dict) or "kind" not in doc:
            raise RecordingError(path, f"frame {index} is not a recording frame")
        yield doc
        index += 1


def read_recording(path: Path | str, allow_incomplete: bool = False) -> Recording:
    """Read and check a recording; ``allow_incomplete`` accepts a crashed recorder's
    ``.partial`` file up to its last complete frame."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(path, "file does not exist") from None
    except OSError as exc:
        raise RecordingError(path, f"cannot read: {exc.strerror}") from None
    if not data.startswith(MAGIC):
        raise RecordingError(path, "not a swarmmap LiDAR recording (bad magic; expected SWMREC01)")
    reader = _Frames(path)
    try:
        for doc in _frames(path, data):
            reader.take(doc)
    except RecordingError as exc:
        if not (allow_incomplete and exc.problem.startswith("truncated")) or reader.header is None:
            raise
    header, frames, footer, digest = reader.header, reader.frames, reader.footer, reader.digest
    if header is None:
        raise RecordingError(path, "no header frame")
    if footer is None:
        if not allow_incomplete:
            raise RecordingError(path, f"incomplete: no footer (the recorder did not finish); {len(frames)} frames "
                                       "are readable with allow_incomplete")
    elif footer.get("frames") != len(frames) or footer.get("sha256") != digest.hexdigest():
        raise RecordingError(path, f"footer says {footer.get('frames')} frames and digest {str(footer.get('sha256'))[:12]}..., "
                                   f"the file holds {len(frames)} with digest {digest.hexdigest()[:12]}...")
    return Recording(path, header, frames, footer is not None)


class _Frames:
    """A recording's frames in order, checked one by one: a header, samples, a footer."""

    def __init__(self, path: Path):
        self.path = path
        self.header: dict[str, Any] | None = None
        self.frames: list[tuple[float, bytes]] = []
        self.footer: dict[str, Any] | None = None
        self.digest = hashlib.sha256()

    def take(self, doc: dict[str, Any]) -> None:
        kind, path = doc["kind"], self.path
        if self.header is None:
            if kind != "header" or doc.get("v") != VERSION:
                raise RecordingError(path, f"first frame must be a version {VERSION} header, got {kind!r} v{doc.get('v')!r}")
            if not isinstance(doc.get("robot"), int) or not isinstance(doc.get("config"), dict):
                raise RecordingError(path, "header lacks its robot id or config")
            self.header = doc
        elif self.footer is not None:
            raise RecordingError(path, "frames after the footer")
        elif kind == "samples" and isinstance(doc.get("payload"), bytes) and isinstance(doc.get("t"), float | int):
            self.frames.append((float(doc["t"]), doc["payload"]))
            self.digest.update(doc["payload"])
        elif kind == "footer":
            self.footer = doc
        else:
            raise RecordingError(path, f"frame {len(self.frames) + 1} has kind {kind!r} or lacks its fields")
