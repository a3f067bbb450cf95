"""LiDAR recordings: whole or visibly incomplete, read back exactly, corruption named."""

from __future__ import annotations

import numpy as np
import pytest

from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Samples, Tensor
from swarmmap.shared.world.recording import RecordingError, RecordingWriter, read_recording


def samples(i: int, last: bool = False) -> bytes:
    rng = np.random.default_rng(i)
    return encode(Samples(run="rec", sender=2, seq=i, t=0.2 * i, position=[0.0, 1.0],
                          points=Tensor.of(rng.standard_normal((50, 2)).astype(np.float32)),
                          labels=Tensor.of((rng.uniform(size=50) > 0.8).astype(np.float32)), last=last))


def record(path, n=5, close=True):
    w = RecordingWriter(path, robot=2, config={"run_id": "rec", "seed": 3}, plan={"floorplan": "procedural"})
    payloads = [samples(i, last=i == n - 1) for i in range(n)]
    for p in payloads:
        w.add(p)
    if close:
        w.close()
    else:
        w.abandon()
    return payloads


def test_round_trip_is_byte_identical(tmp_path):
    path = tmp_path / "robot-2.swrec"
    payloads = record(path)
    rec = read_recording(path)
    assert rec.complete and rec.robot == 2 and rec.config == {"run_id": "rec", "seed": 3}
    assert rec.header["plan"] == {"floorplan": "procedural"}
    assert [p for _, p in rec.frames] == payloads
    assert all(b >= a for (a, _), (b, _) in zip(rec.frames, rec.frames[1:]))
    assert not (tmp_path / "robot-2.swrec.partial").exists()


def test_a_crash_leaves_only_a_partial_file_whose_frames_are_kept(tmp_path):
    path = tmp_path / "robot-2.swrec"
    payloads = record(path, close=False)
    assert not path.exists(), "an unfinished recording must not look whole"
    partial = tmp_path / "robot-2.swrec.partial"
    with pytest.raises(RecordingError, match="incomplete: no footer"):
        read_recording(partial)
    rec = read_recording(partial, allow_incomplete=True)
    assert not rec.complete and [p for _, p in rec.frames] == payloads
    # A frame cut in half by the crash: the frames before it survive.
    data = partial.read_bytes()
    partial.write_bytes(data[:-40])
    rec = read_recording(partial, allow_incomplete=True)
    assert [p for _, p in rec.frames] == payloads[:-1]


def test_truncated_corrupt_and_foreign_files_are_named(tmp_path):
    path = tmp_path / "r.swrec"
    record(path)
    data = path.read_bytes()
    path.write_bytes(data[:-10])
    with pytest.raises(RecordingError, match="r.swrec: truncated"):
        read_recording(path)
    corrupt = bytearray(data)
    corrupt[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(corrupt))
    with pytest.raises(RecordingError, match="checksum mismatch"):
        read_recording(path)
    path.write_bytes(b"PK\x03\x04 a zip file")
    with pytest.raises(RecordingError, match="not a swarmmap LiDAR recording"):
        read_recording(path)
    with pytest.raises(RecordingError, match="missing.swrec: file does not exist"):
        read_recording(tmp_path / "missing.swrec")
