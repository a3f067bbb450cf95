"""What a bag's compressed chunks may expand to, checked before a bag reader opens it.

A bag's reader (rosbags) inflates each chunk whole and trusts neither nor checks the size the
chunk states: a 33 KB MCAP whose zstd chunk expands to 1 GiB took 2.17 GB and two minutes
before it failed. :func:`check_chunks` walks the chunks of an MCAP file (``.mcap``) or a ROS 1
bag (``.bag``), each in turn, and refuses (ValueError naming the chunk) one that states or
inflates to more than MAX_CHUNK_BYTES, or that inflates to more than it states; inflating is
streamed INFLATE_STEP bytes at a time, so the check holds at most that much at once.
"""

from __future__ import annotations

import bz2
import struct
import sys
from pathlib import Path
from typing import BinaryIO

MAX_CHUNK_BYTES = 256 << 20  # a chunk of a bag, inflated (MCAP writers make chunks of about 1-4 MB)
INFLATE_STEP = 8 << 20
MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"


def _decompressor(kind: str):
    """A streaming decompressor of ``kind`` with ``decompress(data, max_length)``; None for none."""
    if kind in ("", "none"):
        return None
    if kind == "zstd":
        if sys.version_info >= (3, 14):
            from compression import zstd
        else:  # pragma: no cover - the backport rosbags depends on
            from backports import zstd
        return zstd.ZstdDecompressor()
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor()
    if kind == "bz2":
        return bz2.BZ2Decompressor()
    raise ValueError(f"unknown compression {kind!r}")


def inflated_size(kind: str, data: bytes, stated: int, limit: int = MAX_CHUNK_BYTES) -> int:
    """How many bytes ``data`` inflates to, counted INFLATE_STEP at a time; a ValueError once it
    exceeds ``stated`` or ``limit``."""
    d = _decompressor(kind)
    if d is None:
        return len(data)
    total, chunk = 0, data
    cap = min(stated, limit)
    while True:
        out = d.decompress(chunk, max_length=INFLATE_STEP)
        total += len(out)
        if total > cap:
            raise ValueError(f"it inflates to more than {cap} bytes (it states {stated})")
        chunk = b""
        if getattr(d, "eof", False) or getattr(d, "needs_input", True):  # the stream's end, or all of it inflated
            return total


def _check(stated: int, kind: str, data: bytes, where: str) -> None:
    if stated > MAX_CHUNK_BYTES:
        raise ValueError(f"{where} states {stated} bytes inflated, more than {MAX_CHUNK_BYTES}")
    try:
        inflated_size(kind, data, stated)
    except ValueError as exc:
        raise ValueError(f"{where} ({kind}): {exc}") from None
    except Exception as exc:  # a damaged stream: the decompressors raise their own errors
        raise ValueError(f"{where} ({kind}) cannot be inflated: {type(exc).__name__}: {exc}") from None


def _read(f: BinaryIO, n: int, where: str, left: int) -> bytes:
    """``n`` bytes of ``f``, of which ``left`` remain where they are read (a stated length past
    them is refused before anything is set aside for it)."""
    if n > left:
        raise ValueError(f"{where} states {n} bytes where {left} remain")
    data = f.read(n)
    if len(data) != n:
        raise ValueError(f"{where}: cut short")
    return data


def check_mcap(path: Path) -> int:
    """Walk an MCAP file's records and check each chunk; returns how many there are."""
    size = path.stat().st_size
    with path.open("rb") as f:
        if f.read(8) != MCAP_MAGIC:
            return 0  # not an MCAP file: its reader says so
        chunks = 0
        while f.tell() < size - 8:
            head = f.read(9)
            if len(head) < 9:
                break
            opcode, length = head[0], struct.unpack("<Q", head[1:])[0]
            where = f"chunk {chunks} at byte {f.tell() - 9}"
            if opcode == 0x02:  # the footer: the data section is over
                break
            if opcode != 0x06:  # not a chunk
                if length > size - f.tell():
                    raise ValueError(f"a record at byte {f.tell() - 9} states {length} bytes, more than the file holds")
                f.seek(length, 1)
                continue
            content = _read(f, length, where, size - f.tell())
            if len(content) < 40:
                raise ValueError(f"{where}: cut short")
            _, _, stated, _, kind_len = struct.unpack_from("<QQQII", content)
            kind = content[32 : 32 + kind_len].decode(errors="replace")
            at = 32 + kind_len
            if at + 8 > len(content):
                raise ValueError(f"{where}: cut short")
            records = struct.unpack_from("<Q", content, at)[0]
            if records > len(content) - at - 8:
                raise ValueError(f"{where} states {records} bytes of records, more than it holds")
            _check(stated, kind, content[at + 8 : at + 8 + records], where)
            chunks += 1
        return chunks


def _ros1_fields(header: bytes) -> dict[str, bytes]:
    fields, at = {}, 0
    while at + 4 <= len(header):
        n = struct.unpack_from("<I", header, at)[0]
        name, _, value = header[at + 4 : at + 4 + n].partition(b"=")
        fields[name.decode(errors="replace")] = value
        at += 4 + n
    return fields


def check_ros1(path: Path) -> int:
    """Walk a ROS 1 bag's records and check each chunk; returns how many there are."""
    with path.open("rb") as f:
        if f.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
            return 0
        size = path.stat().st_size
        chunks = 0
        while f.tell() < size:
            where = f"record at byte {f.tell()}"
            header_len = struct.unpack("<I", _read(f, 4, where, size - f.tell()))[0]
            fields = _ros1_fields(_read(f, header_len, where, size - f.tell()))
            data_len = struct.unpack("<I", _read(f, 4, where, size - f.tell()))[0]
            if fields.get("op") == b"\x05":  # a chunk
                stated = struct.unpack("<I", fields.get("size", b"\0\0\0\0")[:4].ljust(4, b"\0"))[0]
                kind = fields.get("compression", b"none").decode(errors="replace")
                _check(stated, kind, _read(f, data_len, where, size - f.tell()), f"chunk {chunks} at byte {f.tell() - data_len}")
                chunks += 1
            else:
                if data_len > size - f.tell():
                    raise ValueError(f"{where} states {data_len} bytes of data where {size - f.tell()} remain")
                f.seek(data_len, 1)
        return chunks


def check_chunks(path: Path) -> None:
    """Check every MCAP file and ROS 1 bag at ``path`` (a file, or a rosbag2 folder's files)."""
    files = sorted(path.iterdir()) if path.is_dir() else [path]
    for p in files:
        if p.suffix == ".mcap":
            check_mcap(p)
        elif p.suffix == ".bag":
            check_ros1(p)
