"""The swarmmap wire protocol: every key expression and every message, in one module.

Keys live under ``<prefix>/<run>/`` (see :class:`Keys`). Every payload is one msgpack map
with a schema version ``v`` and a ``kind``; tensors travel as ``{"dtype", "shape", "data"}``
with raw little-endian bytes, never pickle. :func:`decode` refuses anything malformed,
oversized, from another run, from a sender that does not match its key, of the wrong shape
or dtype, or non-finite, by raising :class:`ProtocolError` with a short reason.
The README's "Wire protocol" section documents all of this for clients in other languages.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

SCHEMA_VERSION = 1
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024

NAME_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
_NAME_RE = re.compile(NAME_PATTERN)

# Little-endian dtype strings a tensor may carry ("|u1" has no byte order).
TENSOR_DTYPES = ("<f4", "<f8", "<i4", "<i8", "|u1")
MAX_TENSOR_DIMS = 4


class ProtocolError(ValueError):
    """A payload that a receiver refuses; ``reason`` is a short tag used for counting."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


# ----------------------------------------------------------------------------- key expressions


def check_name(value: str, what: str) -> str:
    """Return ``value`` if it is a safe key-expression chunk (no ``/``, ``*``, ``$``...)."""
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise ValueError(f"{what} must match {NAME_PATTERN} (letters, digits, _ . -), got {value!r}")
    return value


class Keys:
    """Builds every key expression of one run; no service writes a key string inline.

    Layout under ``<prefix>/<run>``::

        robots/<id>/scan            Scan        world -> lidar
        robots/<id>/samples         Samples     lidar -> learner
        learners/<id>/state         State       learner -> neighbours (Algorithm 1)
        learners/<id>/round-complete RoundComplete learner -> neighbours (Algorithm 1)
        learners/<id>/metrics       Metrics     learner -> launcher, observer
        world/map                   WorldMap    queryable served by the world
        run/done                    RunDone     recorder -> every service: the run is over
        alive/<service>/<id>        liveliness tokens of every service
    """

    def __init__(self, prefix: str, run: str):
        self.prefix = "/".join(check_name(part, "key prefix part") for part in prefix.split("/"))
        self.run = check_name(run, "run id")
        self.root = f"{self.prefix}/{self.run}"

    def scan(self, robot: int | str) -> str:
        return f"{self.root}/robots/{robot}/scan"

    def samples(self, robot: int | str) -> str:
        return f"{self.root}/robots/{robot}/samples"

    def state(self, robot: int | str) -> str:
        return f"{self.root}/learners/{robot}/state"

    def round_complete(self, robot: int | str) -> str:
        return f"{self.root}/learners/{robot}/round-complete"

    def metrics(self, robot: int | str) -> str:
        return f"{self.root}/learners/{robot}/metrics"

    def world_map(self) -> str:
        return f"{self.root}/world/map"

    def run_done(self) -> str:
        return f"{self.root}/run/done"

    def alive(self, service: str = "*", ident: int | str = "*") -> str:
        return f"{self.root}/alive/{service}/{ident}"

    def everything(self) -> str:
        return f"{self.root}/**"

    def parse_alive(self, key: str) -> tuple[str, str]:
        """``.../alive/<service>/<id>`` -> ``(service, id)``."""
        tail = key[len(self.root) + 1 :].split("/")
        if not key.startswith(self.root + "/") or len(tail) != 3 or tail[0] != "alive":
            raise ValueError(f"not a liveliness key of run {self.run!r}: {key!r}")
        return tail[1], tail[2]

    def ident_of(self, key: str) -> int:
        """The numeric id in ``.../robots/<id>/...`` or ``.../learners/<id>/...``."""
        tail = key[len(self.root) + 1 :].split("/")
        if not key.startswith(self.root + "/") or len(tail) < 3 or not tail[1].isdigit():
            raise ProtocolError("bad-key", f"key {key!r} carries no numeric id under {self.root!r}")
        return int(tail[1])


# ----------------------------------------------------------------------------- tensors


class Tensor(BaseModel):
    """An n-d array on the wire: raw little-endian bytes plus dtype and shape."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dtype: Literal[TENSOR_DTYPES]  # type: ignore[valid-type]
    shape: Annotated[list[Annotated[int, Field(ge=0)]], Field(max_length=MAX_TENSOR_DIMS)]
    data: bytes

    @model_validator(mode="after")
    def _check(self) -> Tensor:
        expected = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if len(self.data) != expected:
            raise ValueError(f"data has {len(self.data)} bytes, dtype {self.dtype} shape {self.shape} needs {expected}")
        if self.dtype[1] == "f" and not np.isfinite(self.numpy()).all():
            raise ValueError("non-finite values")
        return self

    def numpy(self) -> np.ndarray:
        """A read-only view of the data (copy it before writing)."""
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype)).reshape(self.shape)

    @classmethod
    def of(cls, array: Any, dtype: str | None = None) -> Tensor:
        """Encode a numpy array (or anything array-like, a torch tensor on the CPU too)."""
        arr = np.asarray(array)
        if dtype is not None:
            arr = arr.astype(np.dtype(dtype), copy=False)
        arr = np.ascontiguousarray(arr.astype(arr.dtype.newbyteorder("<"), copy=False))
        code = arr.dtype.str
        return cls(dtype=code, shape=list(arr.shape), data=arr.tobytes())


def _require(t: Tensor, name: str, dtype: str, ndim: int, trailing: tuple[int, ...] = ()) -> None:
    if t.dtype != dtype:
        raise ValueError(f"{name} must have dtype {dtype}, got {t.dtype}")
    if len(t.shape) != ndim or tuple(t.shape[ndim - len(trailing) :]) != trailing:
        raise ValueError(f"{name} must have shape (n{', ' + ', '.join(map(str, trailing)) if trailing else ''}), got {tuple(t.shape)}")


# ----------------------------------------------------------------------------- messages

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
RobotId = Annotated[int, Field(ge=0, le=9999)]
Round = Annotated[int, Field(ge=0, le=10**9)]


class Message(BaseModel):
    """Fields every message carries: schema version, kind, run id and sender id."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    KIND: ClassVar[str] = ""

    v: Literal[1] = SCHEMA_VERSION
    kind: str
    run: Annotated[str, Field(pattern=NAME_PATTERN)]
    sender: RobotId

    def __init__(self, **data: Any):
        data.setdefault("kind", self.KIND)
        super().__init__(**data)

    @field_validator("kind")
    @classmethod
    def _kind(cls, value: str) -> str:
        if value != cls.KIND:
            raise ValueError(f"kind must be {cls.KIND!r}, got {value!r}")
        return value


class Scan(Message):
    """One raw LiDAR scan of a robot, world -> lidar. ``hit[i]`` is 0 where beam i saw nothing
    within ``max_range`` (its range is then ``max_range``)."""

    KIND: ClassVar[str] = "Scan"
    seq: Annotated[int, Field(ge=0)]
    t: FiniteFloat
    pose: Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
    max_range: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    angles: Tensor
    ranges: Tensor
    hit: Tensor
    last: bool = False

    @model_validator(mode="after")
    def _shapes(self) -> Scan:
        for name in ("angles", "ranges"):
            _require(getattr(self, name), name, "<f4", 1)
        _require(self.hit, "hit", "|u1", 1)
        if not (self.angles.shape == self.ranges.shape == self.hit.shape):
            raise ValueError("angles, ranges and hit must have the same length")
        return self


class Samples(Message):
    """Labelled training points from one scan, lidar -> learner: label 0 = free, 1 = occupied."""

    KIND: ClassVar[str] = "Samples"
    seq: Annotated[int, Field(ge=0)]
    t: FiniteFloat
    position: Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)]
    points: Tensor
    labels: Tensor
    last: bool = False

    @model_validator(mode="after")
    def _shapes(self) -> Samples:
        _require(self.points, "points", "<f4", 2, (2,))
        _require(self.labels, "labels", "<f4", 1)
        if self.points.shape[0] != self.labels.shape[0]:
            raise ValueError("points and labels must have the same length")
        labels = self.labels.numpy()
        if ((labels < 0) | (labels > 1)).any():
            raise ValueError("labels must lie in [0, 1]")
        return self


class State(Message):
    """Algorithm 1's State message: a learner's flattened parameters at the start of ``round``."""

    KIND: ClassVar[str] = "State"
    round: Round
    params: Tensor

    @model_validator(mode="after")
    def _shapes(self) -> State:
        _require(self.params, "params", "<f4", 1)
        return self


class RoundComplete(Message):
    """Algorithm 1's RoundComplete message: the sender finished its node update of ``round``."""

    KIND: ClassVar[str] = "RoundComplete"
    round: Round


class Metrics(Message):
    """A learner's evaluation at ``round``; ``final`` marks the last one of its run."""

    KIND: ClassVar[str] = "Metrics"
    round: Round
    wall_time_s: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    val_bce: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    consensus_error: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    bytes_sent: Annotated[int, Field(ge=0)]
    bytes_received: Annotated[int, Field(ge=0)]
    compute_s: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    wait_s: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    send_s: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    n_points: Annotated[int, Field(ge=0)] = 0
    pid: Annotated[int, Field(ge=0)] = 0
    refused: Annotated[int, Field(ge=0)] = 0
    final: bool = False


class WorldMap(Message):
    """The world's reply on ``world/map``: the ground-truth occupancy grid and a validation set.

    ``grid[r, c]`` (1 = occupied) covers x in [origin_x + c*res, +res) and y in
    [origin_y + r*res, +res): row 0 is the southern edge (y up). ``val_labels`` come from the
    ground truth, never from a sensor. ``positions`` (robots, 2) are where the robots stand
    after their traversal (for distance-based communication graphs). ``sender`` is 0."""

    KIND: ClassVar[str] = "WorldMap"
    resolution: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    origin: Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)]
    grid: Tensor
    val_points: Tensor
    val_labels: Tensor
    robots: Annotated[int, Field(ge=1, le=10000)]
    positions: Tensor | None = None

    @model_validator(mode="after")
    def _shapes(self) -> WorldMap:
        _require(self.grid, "grid", "|u1", 2)
        if self.positions is not None:
            _require(self.positions, "positions", "<f4", 2, (2,))
            if self.positions.shape[0] != self.robots:
                raise ValueError("positions must hold one row per robot")
        _require(self.val_points, "val_points", "<f4", 2, (2,))
        _require(self.val_labels, "val_labels", "<f4", 1)
        if self.val_points.shape[0] != self.val_labels.shape[0]:
            raise ValueError("val_points and val_labels must have the same length")
        return self

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the grid in metres."""
        h, w = self.grid.shape
        x0, y0 = self.origin
        return x0, y0, x0 + w * self.resolution, y0 + h * self.resolution


class RunDone(Message):
    """The recorder's word that the run is over, to every service (``sender`` is 0): ``ok`` when
    every learner finished, else ``reason`` names what failed. Services exit on it."""

    KIND: ClassVar[str] = "RunDone"
    ok: bool
    reason: Annotated[str, Field(max_length=2000)]
    finished: Annotated[list[RobotId], Field(max_length=10000)] = []


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.KIND: cls for cls in (Scan, Samples, State, RoundComplete, Metrics, WorldMap, RunDone)
}

M = TypeVar("M", bound=Message)


# ----------------------------------------------------------------------------- codec


def encode(message: Message) -> bytes:
    """Serialise a message to its msgpack bytes."""
    if isinstance(message, State) and isinstance(message.params.data, memoryview):  # decoded by the fast path
        return encode_state(message.run, message.sender, message.round, message.params.numpy())
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def _bin_header(size: int) -> bytes:
    """msgpack's bin header for ``size`` bytes (the smallest of bin8, bin16, bin32, as packb writes)."""
    if size < 1 << 8:
        return b"\xc4" + size.to_bytes(1, "big")
    if size < 1 << 16:
        return b"\xc5" + size.to_bytes(2, "big")
    return b"\xc6" + size.to_bytes(4, "big")


def encode_state(run: str, sender: int, round: int, params: np.ndarray) -> bytes:
    """``encode(State(run=..., sender=..., round=..., params=Tensor.of(params, "<f4")))`` byte for
    byte, with one copy of the vector and no pass over it: Algorithm 1's hot path. The small
    fields are checked as :class:`State` checks them; finiteness is left to the receivers,
    which refuse a non-finite vector (a pass over 2 MB costs as much as the copy)."""
    arr = np.ascontiguousarray(params, dtype="<f4")
    if arr.ndim != 1:
        raise ValueError(f"State.params must be one-dimensional, got shape {arr.shape}")
    if not _NAME_RE.match(run) or not 0 <= sender <= 9999 or not 0 <= round <= 10**9:
        raise ValueError(f"invalid State header: run {run!r}, sender {sender}, round {round}")
    head = msgpack.packb({"v": SCHEMA_VERSION, "kind": State.KIND, "run": run, "sender": int(sender), "round": int(round),
                          "params": {"dtype": "<f4", "shape": [arr.shape[0]], "data": b""}}, use_bin_type=True)
    return b"".join((head[:-2], _bin_header(arr.nbytes), memoryview(arr).cast("B")))


_DATA_KEY = b"\xa4data"
_STATE_KEYS = {"v", "kind", "run", "sender", "round", "params"}


def _decode_state_fast(payload: bytes, run: str, sender: int | None) -> State | None:
    """A State in exactly the layout :func:`encode_state` writes, without copying its vector:
    the header is checked field by field and the vector is a read-only view of ``payload``.
    Anything else (another layout, a bad field, a non-finite value) returns None, and
    :func:`decode`'s full validation decides (and names the reason)."""
    at = payload.find(_DATA_KEY, 0, 256)  # run names cannot hold 0xa4, so this is the key
    if at < 0 or at + 5 >= len(payload):
        return None
    marker, start = payload[at + 5], at + 6
    width = {0xC4: 1, 0xC5: 2, 0xC6: 4}.get(marker)
    if width is None:
        return None
    size = int.from_bytes(payload[start : start + width], "big")
    start += width
    if start + size != len(payload) or size % 4:
        return None
    try:
        doc = msgpack.unpackb(payload[:at] + _DATA_KEY + b"\xc4\x00", raw=False, strict_map_key=True,
                              max_str_len=1 << 10, max_array_len=16, max_map_len=16, max_ext_len=0)
    except Exception:
        return None
    if not isinstance(doc, dict) or doc.keys() != _STATE_KEYS or not isinstance(doc["params"], dict):
        return None
    params, shape = doc["params"], doc["params"].get("shape")
    ints = (doc["sender"], doc["round"])
    if (doc["v"] != SCHEMA_VERSION or doc["kind"] != State.KIND or doc["run"] != run
            or any(type(i) is not int for i in ints) or not 0 <= doc["sender"] <= 9999 or not 0 <= doc["round"] <= 10**9
            or (sender is not None and doc["sender"] != sender) or params.keys() != {"dtype", "shape", "data"}
            or params["dtype"] != "<f4" or shape != [size // 4]):
        return None
    view = np.frombuffer(payload, dtype="<f4", count=size // 4, offset=start)
    if not np.isfinite(view).all():  # (no BLAS here: its threads would spin beside Zenoh's)
        return None
    tensor = Tensor.model_construct(dtype="<f4", shape=shape, data=memoryview(payload)[start:])
    return State.model_construct(v=SCHEMA_VERSION, kind=State.KIND, run=run, sender=doc["sender"], round=doc["round"],
                                 params=tensor)


def decode(
    payload: bytes,
    expected: type[M],
    *,
    run: str,
    sender: int | None = None,
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
) -> M:
    """Decode and validate one payload as ``expected``; raise :class:`ProtocolError` if refused.

    ``sender`` (when given) is the id named by the key the payload arrived on: a message whose
    own ``sender`` differs is refused, so nobody can speak for another robot.
    """
    if len(payload) > max_bytes:
        raise ProtocolError("oversized", f"{len(payload)} bytes > limit {max_bytes}")
    if expected is State and isinstance(payload, bytes):
        fast = _decode_state_fast(payload, run, sender)
        if fast is not None:
            return fast  # type: ignore[return-value]
    try:
        doc = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_bin_len=max_bytes,
            max_str_len=1 << 16,
            max_array_len=1 << 16,
            max_map_len=256,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise ProtocolError("malformed", f"not msgpack: {exc}") from None
    if not isinstance(doc, dict):
        raise ProtocolError("malformed", f"top level must be a map, got {type(doc).__name__}")
    if doc.get("v") != SCHEMA_VERSION:
        raise ProtocolError("version", f"schema version {doc.get('v')!r}, this build speaks {SCHEMA_VERSION}")
    if doc.get("kind") != expected.KIND:
        raise ProtocolError("kind", f"expected {expected.KIND}, got {doc.get('kind')!r}")
    if doc.get("run") != run:
        raise ProtocolError("wrong-run", f"run {doc.get('run')!r}, expected {run!r}")
    if sender is not None and doc.get("sender") != sender:
        raise ProtocolError("unknown-sender", f"sender {doc.get('sender')!r} on a key of {sender}")
    try:
        return expected.model_validate(doc)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or expected.KIND
        reason = "non-finite" if "finite" in first["msg"] else "invalid"
        if "shape" in first["msg"] or "dtype" in first["msg"] or "bytes" in first["msg"]:
            reason = "shape"
        raise ProtocolError(reason, f"{expected.KIND}.{where}: {first['msg']}") from None
