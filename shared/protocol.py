"""The swarmmap wire protocol: every key expression and every message, in one module.

Keys live under ``<prefix>/<run>/`` (see :class:`Keys`). Every payload is one msgpack map
with a schema version ``v`` and a ``kind``; tensors travel as ``{"dtype", "shape", "data"}``
with raw little-endian bytes, never pickle. :func:`decode` refuses anything malformed,
oversized, from another run, from a sender that does not match its key, of the wrong shape
or dtype, or non-finite, by raising :class:`ProtocolError` with a short reason.
The README's "Wire protocol" section documents all of this for clients in other languages.
"""

from __future__ import annotations

import functools
import math
import re
import sys
import warnings
from dataclasses import dataclass, fields
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

SCHEMA_VERSION = 2
# Versions read per message kind: a State changed in version 2 (compressed encodings), the other
# messages did not, so that those of version 1 (a recording made by an older build) are still read.
READ_VERSIONS = {"State": (2,)}
OLDEST_VERSION = 1
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024

NAME_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
_NAME_RE = re.compile(NAME_PATTERN)

# Little-endian dtype strings a tensor may carry ("|u1" has no byte order).
TENSOR_DTYPES = ("<f4", "<f8", "<f2", "<i4", "<i8", "<u2", "<u4", "|u1")
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

    def learner(self, robot: int | str) -> str:
        """Every key learner ``robot`` publishes on (``learners/<id>/*``)."""
        return f"{self.root}/learners/{robot}/*"

    def exchange(self, robot: int | str) -> tuple[str, str]:
        """Algorithm 1's keys of ``robot``: its State and its RoundComplete."""
        return self.state(robot), self.round_complete(robot)

    def is_exchange(self, key: str) -> bool:
        """Whether ``key`` is some learner's State or RoundComplete key of this run."""
        tail = key[len(self.root) + 1 :].split("/")
        return key.startswith(self.root + "/") and len(tail) == 3 and tail[0] == "learners" and tail[2] in (
            "state", "round-complete")

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

    v: Literal[1, 2] = SCHEMA_VERSION
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


STATE_ENCODINGS = ("f32", "f16", "bf16", "topk", "sign", "quant", "lowrank")
CHAINED_ENCODINGS = ("topk", "sign", "quant", "lowrank")  # each such State adds to the sender's previous one
SCALE_CHUNK = 256  # values per scale of a sign or quant State
MAX_COVERAGE_BYTES = 1 << 20  # a State's coverage bits: 8.4 M cells (a 1 km x 1 km map at 0.35 m)


class State(Message):
    """Algorithm 1's State message: a learner's flattened parameters at the start of ``round``.

    ``encoding`` says how ``params`` holds the vector (``learner.compression``):

    - ``f32`` (default): the vector, float32 (``<f4``).
    - ``f16``: the vector rounded to IEEE half precision (``<f2``).
    - ``bf16``: the vector rounded to bfloat16, as the top 16 bits of each float32 (``<u2``).
    - ``topk``: a sparse update of the sender's vector as its receivers hold it: ``params`` the
      values (``<f4``) to add at ``indices`` (``<u4``, strictly increasing, below ``size``) to
      the vector of the sender's State numbered ``base``; this State is numbered ``seq``. An
      ``f32`` State with a ``seq`` starts such a chain again (a key frame).
    - ``sign``: the same chain, dense: ``params`` (``|u1``) packs one bit per value (numpy's
      packbits, most significant bit first; 1 = add, 0 = subtract) and ``scales`` (``<f4``)
      holds the step of each run of SCALE_CHUNK values, to add to the State numbered ``base``.
    - ``quant``: the same chain, dense: ``params`` (``|u1``) is a raw deflate stream (RFC 1951)
      of one code c per value, below 2^``bits`` (``bits`` 2-16; a byte each up to 8 bits, else
      two, little-endian); the value added is
      (c - 2^(bits-1) + 1) x the step in ``scales`` (``<f4``) of its run of SCALE_CHUNK values.
      Without ``base``, the State is a key frame: the codes stand for the vector itself. A
      stream that does not inflate to exactly ``size`` such codes is refused by the receiver.
    - ``lowrank``: the same chain, each weight matrix's update as a product of two thin
      factors (PowerGossip-like): ``blocks`` lists [offset, rows, cols, rank] per matrix
      (row-major at ``offset`` in the vector, by increasing offset, not overlapping, rank at
      most min(rows, cols)); ``params`` (``<f4``) holds, block by block, P (rows x rank) then
      Q (cols x rank), row-major, the update being P Q^T; then the update of every value no
      block covers, in order.

    ``position`` [x, y] (m), where the sender's robot is, comes with a dynamic disk graph
    (``learner.graph`` disk with ``learner.data`` online): receivers out of range ignore it.

    ``coverage`` (``|u1``, at most MAX_COVERAGE_BYTES), with ``learner.unseen_weight`` and
    ``learner.share_coverage``: the cells of the map the sender knows some robot has data near,
    one bit per cell of a grid of ``unseen_margin_m / 2`` over the map's bounds (row-major from
    the bounds' lower corner, numpy's packbits order); receivers merge it into theirs (a
    length that does not fit their grid is ignored, with a warning)."""

    KIND: ClassVar[str] = "State"
    v: Literal[2] = SCHEMA_VERSION
    round: Round
    params: Tensor
    encoding: Literal[STATE_ENCODINGS] = "f32"  # type: ignore[valid-type]
    size: Annotated[int, Field(ge=0, lt=1 << 30)] | None = None
    indices: Tensor | None = None
    seq: Annotated[int, Field(ge=0)] | None = None
    base: Annotated[int, Field(ge=0)] | None = None
    position: Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)] | None = None
    scales: Tensor | None = None
    bits: Annotated[int, Field(ge=2, le=16)] | None = None
    blocks: Annotated[list[Annotated[list[Annotated[int, Field(ge=0, lt=1 << 30)]], Field(min_length=4, max_length=4)]],
                      Field(max_length=4096)] | None = None
    coverage: Tensor | None = None

    @model_validator(mode="after")
    def _shapes(self) -> State:
        if self.coverage is not None:
            _require(self.coverage, "coverage", "|u1", 1)
            if self.coverage.shape[0] > MAX_COVERAGE_BYTES:
                raise ValueError(f"coverage of {self.coverage.shape[0]} bytes (at most {MAX_COVERAGE_BYTES})")
        dtype = {"f32": "<f4", "f16": "<f2", "bf16": "<u2", "topk": "<f4", "sign": "|u1", "quant": "|u1",
                 "lowrank": "<f4"}[self.encoding]
        _require(self.params, "params", dtype, 1)
        if self.encoding == "bf16" and (self.params.numpy() & 0x7F80 == 0x7F80).any():
            raise ValueError("params: non-finite values")
        if (self.bits is not None) != (self.encoding == "quant"):
            raise ValueError("bits belong to quant States, and every quant State has them")
        if (self.blocks is not None) != (self.encoding == "lowrank"):
            raise ValueError("blocks belong to lowrank States, and every lowrank State has them")
        if self.encoding not in CHAINED_ENCODINGS:
            if any(x is not None for x in (self.indices, self.size, self.base, self.scales)):
                raise ValueError(f"indices, size, base and scales belong to chained States, not {self.encoding}")
            return self
        if self.size is None or self.seq is None or (self.base is None and self.encoding != "quant"):
            raise ValueError(f"a {self.encoding} State needs size, seq and base")
        {"lowrank": self._lowrank_shapes, "sign": self._dense_shapes, "quant": self._dense_shapes,
         "topk": self._topk_shapes}[self.encoding]()
        return self

    def _lowrank_shapes(self) -> None:
        if self.indices is not None or self.scales is not None:
            raise ValueError("a lowrank State has no indices or scales")
        values, end = self.size, 0
        for offset, rows, cols, rank in self.blocks:
            if offset < end or rows * cols > self.size - offset or not 1 <= rank <= min(rows, cols):
                raise ValueError(f"lowrank block [{offset}, {rows}, {cols}, {rank}] overlaps another, runs past size "
                                 f"{self.size} or has a rank outside 1..min(rows, cols)")
            end = offset + rows * cols
            values += rank * (rows + cols) - rows * cols
        if self.params.shape[0] != values:
            raise ValueError(f"a lowrank State of size {self.size} with these blocks needs {values} values")

    def _dense_shapes(self) -> None:
        if self.indices is not None or self.scales is None:
            raise ValueError(f"a {self.encoding} State needs scales and no indices")
        _require(self.scales, "scales", "<f4", 1)
        if self.scales.shape[0] != -(-self.size // SCALE_CHUNK):
            raise ValueError(f"a {self.encoding} State of size {self.size} needs {-(-self.size // SCALE_CHUNK)} scales")
        if self.encoding == "sign" and self.params.shape[0] != -(-self.size // 8):
            raise ValueError(f"a sign State of size {self.size} needs {-(-self.size // 8)} bytes of signs")

    def _topk_shapes(self) -> None:
        if self.indices is None or self.scales is not None:
            raise ValueError("a topk State needs indices, size, seq and base")
        _require(self.indices, "indices", "<u4", 1)
        idx = self.indices.numpy()
        if idx.shape != tuple(self.params.shape):
            raise ValueError("indices and params must have the same length")
        if len(idx) and (int(idx[-1]) >= self.size or (np.diff(idx.astype(np.int64)) <= 0).any()):
            raise ValueError(f"indices must increase strictly and stay below size {self.size}")

    @property
    def vector_size(self) -> int:
        """How many values the vector this State stands for has."""
        return self.size if self.size is not None else self.params.shape[0]

    @property
    def plain(self) -> bool:
        """Whether ``params`` is the whole vector as float32 and nothing else comes with it."""
        return self.encoding == "f32" and self.seq is None and self.position is None and self.coverage is None


@dataclass(frozen=True)
class StateBody:
    """What a State says apart from who sent it for which round: its encoded vector and what may
    come with it (see :class:`State`). A :class:`~swarmmap.shared.compression.Compressor` makes
    one, a learner's codec adds its position or coverage, a link stamps it (:meth:`state`)."""

    params: Tensor
    encoding: str = "f32"
    size: int | None = None
    indices: Tensor | None = None
    seq: int | None = None
    base: int | None = None
    scales: Tensor | None = None
    bits: int | None = None
    blocks: list[list[int]] | None = None
    position: list[float] | None = None
    coverage: Tensor | None = None

    def state(self, run: str, sender: int, round: int) -> State:
        """The State ``sender`` sends for ``round`` of run ``run`` with this body (validated)."""
        return State(run=run, sender=sender, round=round, **{f.name: getattr(self, f.name) for f in fields(self)})


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


MAX_VALIDATION_POINTS = 50_000_000  # what a receiver agrees to draw (a few GB at most)


class ValidationRecipe(BaseModel):
    """How a WorldMap's validation set is drawn from its grid
    (:func:`swarmmap.shared.sensing.validation_set` with these arguments), and figures of the
    world's own draw to check a receiver's by: ``count`` points, ``occupied`` of them labelled 1,
    their mean at ``centroid``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    scans: Annotated[int, Field(ge=1, le=100_000)]
    beams: Annotated[int, Field(ge=1, le=100_000)]
    max_range: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    samples_per_beam: Annotated[int, Field(ge=1, le=10_000)]
    seed: int
    occupied_depth: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    count: Annotated[int, Field(ge=0)]
    occupied: Annotated[int, Field(ge=0)]
    centroid: Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)]

    @model_validator(mode="after")
    def _bounded(self) -> ValidationRecipe:
        if self.scans * self.beams * (self.samples_per_beam + 1) > MAX_VALIDATION_POINTS:
            raise ValueError(f"a validation set of more than {MAX_VALIDATION_POINTS} points")
        if self.occupied > self.count:
            raise ValueError("more occupied validation points than points")
        return self


class WorldMap(Message):
    """The world's reply on ``world/map``: the ground-truth occupancy grid and a validation set.

    The validation set comes either as ``val_points`` and ``val_labels`` or, from a simulated
    world (whose grid is the ground truth), as ``validation``: how to draw it from the grid, a
    few hundred bytes where the points are megabytes (what a team on slow links waits for
    before it trains). :meth:`swarmmap.shared.bus.Bus.world` draws it and checks it against
    the world's figures; a query with the parameter ``points`` asks for the points themselves.

    ``grid[r, c]`` (0 free, 1 occupied, 2 unknown: a ROS map's cells nobody knows, solid in the
    world and never ground truth) covers x in [origin_x + c*res, +res) and y in
    [origin_y + r*res, +res): row 0 is the southern edge (y up). ``val_labels`` come from the
    ground truth, never from a sensor. ``positions`` (robots, 2) are where the robots stand
    after their traversal (for distance-based communication graphs). ``sender`` is 0.

    A run on a real log has no ground truth: ``reference`` (float32, the grid's shape) is then
    the classic log-odds grid's occupancy probability from the training scans, ``grid`` its
    trinary map (map_saver's thresholds), and the validation set is the held-out scans' beams,
    labelled along each beam (free before the hit, occupied at it)."""

    KIND: ClassVar[str] = "WorldMap"
    resolution: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    origin: Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)]
    grid: Tensor
    val_points: Tensor | None = None
    val_labels: Tensor | None = None
    robots: Annotated[int, Field(ge=1, le=10000)]
    positions: Tensor | None = None
    reference: Tensor | None = None
    validation: ValidationRecipe | None = None

    @model_validator(mode="after")
    def _shapes(self) -> WorldMap:
        _require(self.grid, "grid", "|u1", 2)
        if self.reference is not None:
            _require(self.reference, "reference", "<f4", 2)
            if self.reference.shape != self.grid.shape:
                raise ValueError("reference must have the grid's shape")
        if self.positions is not None:
            _require(self.positions, "positions", "<f4", 2, (2,))
            if self.positions.shape[0] != self.robots:
                raise ValueError("positions must hold one row per robot")
        if (self.val_points is None) != (self.val_labels is None):
            raise ValueError("val_points and val_labels come together")
        if (self.val_points is None) == (self.validation is None):
            raise ValueError("a validation set comes as val_points and val_labels or as validation, not both")
        if self.val_points is not None and self.val_labels is not None:
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
    """Serialise a message to its msgpack bytes (a State's float32 vector in the layout of
    :func:`encode_state`)."""
    if isinstance(message, State):
        if message.plain and message.params.dtype == "<f4" and len(message.params.shape) == 1:
            return encode_state(message.run, message.sender, message.round, message.params.numpy())
    return msgpack.packb(wire_dict(message), use_bin_type=True)


def wire_dict(message: Message) -> dict:
    """The map a message is on the wire: its fields, less a State's unset optional ones (a
    float32 State carries neither ``encoding`` nor the fields of the other encodings)."""
    doc = message.model_dump(mode="python")
    if isinstance(message, State):
        doc = {k: v for k, v in doc.items() if v is not None and not (k == "encoding" and v == "f32")}
    return doc


STATE_ALIGN = 16  # a State's vector starts at a multiple of this many bytes into its payload
_STATE_KEYS_ORDER = ("v", "kind", "run", "sender", "round", "params", "dtype", "shape")


def _msgpack_str(text: str, extra: int = 0) -> bytes:
    """msgpack's str of ``text`` with a header ``extra`` bytes wider than the smallest (0, 1, 2
    or 4 for a short string): the same string to any msgpack reader."""
    raw = text.encode()
    n = len(raw)
    headers = [h for h in (bytes([0xA0 | n]) if n < 32 else None, b"\xd9" + n.to_bytes(1, "big") if n < 1 << 8 else None,
                           b"\xda" + n.to_bytes(2, "big") if n < 1 << 16 else None, b"\xdb" + n.to_bytes(4, "big"))
               if h is not None]
    wider = [h for h in headers if len(h) == len(headers[0]) + extra]
    if not wider:
        raise ValueError(f"no msgpack str header {extra} bytes wider for {text!r}")
    return wider[0] + raw


@functools.lru_cache(maxsize=64)
def _state_head(run: str, sender: int, n: int) -> tuple[bytes, int]:
    """The bytes of a State before its vector, with round 0, and where the round's four bytes
    are. Fixed widths (sender uint16, round and length uint32, bin32) make the head the same
    length for every round; some keys' str headers are widened so that the vector starts at a
    multiple of :data:`STATE_ALIGN` (numpy then reads it in place, without a bounce buffer).
    Any msgpack reader reads it as the map ``encode`` would write."""

    def build(extras: dict[str, int]) -> tuple[bytes, int]:
        def key(k: str) -> bytes:
            return _msgpack_str(k, extras.get(k, 0))

        head = b"".join((b"\x86", key("v"), bytes([SCHEMA_VERSION]), key("kind"), _msgpack_str(State.KIND),
                         key("run"), _msgpack_str(run), key("sender"), b"\xcd" + sender.to_bytes(2, "big"),
                         key("round"), b"\xce"))
        at = len(head)
        head += b"".join((b"\x00\x00\x00\x00", key("params"), b"\x83", key("dtype"), _msgpack_str("<f4"), key("shape"),
                          b"\x91\xce" + n.to_bytes(4, "big"), _DATA_KEY, b"\xc6" + (4 * n).to_bytes(4, "big")))
        return head, at

    pad = -len(build({})[0]) % STATE_ALIGN
    extras = {}
    for k in _STATE_KEYS_ORDER:  # each short key's header can grow by 4, 2 or 1 byte(s)
        extras[k] = next(e for e in (4, 2, 1, 0) if e <= pad)
        pad -= extras[k]
    return build(extras)


def _check_state_fields(run: str, sender: int, round: int, n: int) -> None:
    """What :class:`State` would refuse in the small fields (the fast encoders skip pydantic)."""
    if not _NAME_RE.match(run) or not 0 <= sender <= 9999 or not 0 <= round <= 10**9 or not 0 <= n < 1 << 30:
        raise ValueError(f"invalid State: run {run!r}, sender {sender}, round {round}, {n} values")


def encode_state(run: str, sender: int, round: int, params: np.ndarray) -> bytes:
    """``encode(State(run=..., sender=..., round=..., params=Tensor.of(params, "<f4")))``, with
    one copy of the vector and no pass over it: Algorithm 1's hot path. The small fields are
    checked as :class:`State` checks them; finiteness is left to the receivers, which refuse a
    non-finite vector (a pass over 2 MB costs as much as the copy). A learner that writes its
    parameters straight into a :class:`StateFrame` sends them without even this copy."""
    arr = np.ascontiguousarray(params, dtype="<f4")
    if arr.ndim != 1:
        raise ValueError(f"State.params must be one-dimensional, got shape {arr.shape}")
    _check_state_fields(run, sender, round, arr.shape[0])
    head, at = _state_head(run, int(sender), arr.shape[0])
    return b"".join((head[:at], int(round).to_bytes(4, "big"), head[at + 4 :], memoryview(arr).cast("B")))


class StateFrame(bytearray):
    """A State's whole payload, allocated before its vector is known: :meth:`new` returns the
    vector, writable, inside the payload; the learner writes its parameters there once, and
    :meth:`stamp` sets the round before each send (the payload is the bytes of
    :func:`encode_state`, with no copy)."""

    run: str
    sender: int
    n: int
    _round_at: int
    _address: int

    @classmethod
    def new(cls, run: str, sender: int, n: int) -> np.ndarray:
        """An uninitialised float32 vector of ``n`` values whose buffer is a State's payload."""
        _check_state_fields(run, sender, 0, n)
        head, at = _state_head(run, int(sender), n)
        frame = cls(len(head) + 4 * n)
        frame[: len(head)] = head
        frame.run, frame.sender, frame.n, frame._round_at = run, int(sender), n, at
        view = np.frombuffer(frame, dtype="<f4", count=n, offset=len(head))
        frame._address = view.ctypes.data
        return view

    @staticmethod
    def of(params: np.ndarray) -> StateFrame | None:
        """The frame whose whole vector ``params`` is, or None (any other array)."""
        base = params.base
        if not isinstance(base, memoryview) or not isinstance(base.obj, StateFrame):
            return None
        frame = base.obj
        whole = params.dtype == np.dtype("<f4") and params.shape == (frame.n,) and params.flags.c_contiguous
        return frame if whole and params.ctypes.data == frame._address else None

    def stamp(self, round: int) -> StateFrame:
        """Set the State's round (the payload is then ready to send)."""
        _check_state_fields(self.run, self.sender, round, self.n)
        self[self._round_at : self._round_at + 4] = int(round).to_bytes(4, "big")
        return self


_DATA_KEY = b"\xa4data"

# A decoded State's vector is a read-only view of its payload (no copy), and whoever takes it
# only reads it (torch included, for sums and stacks): torch's warning about tensors over
# non-writable arrays says nothing here.
warnings.filterwarnings("ignore", message="The given NumPy array is not writable", category=UserWarning)


def all_finite(values: np.ndarray) -> bool:
    """Whether every value of a float32 vector is finite, exactly, in as few passes as can be.

    A finite sum proves it (an inf or NaN anywhere makes the sum inf or NaN; the sum of finite
    values is never NaN); a sum that is not finite, which huge finite values can also give, is
    decided by ``np.isfinite``. In a process that has loaded torch (learners, the observer),
    torch sums: one pass that reads the vector, against numpy's isfinite that also writes and
    reads a mask (0.07 against 0.12 ms for the paper's 2.1 MB State, one thread). No BLAS here:
    its threads would spin beside Zenoh's."""
    torch = sys.modules.get("torch")
    if torch is not None and values.dtype == np.float32 and values.size >= 4096:
        total = torch.from_numpy(values).sum().item()
        if math.isfinite(total):
            return True
    return bool(np.isfinite(values).all())
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
    if not all_finite(view):
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
    if doc.get("kind") != expected.KIND:
        raise ProtocolError("kind", f"expected {expected.KIND}, got {doc.get('kind')!r}")
    readable = READ_VERSIONS.get(expected.KIND, range(OLDEST_VERSION, SCHEMA_VERSION + 1))
    if doc.get("v") not in readable:
        older = isinstance(doc.get("v"), int) and doc["v"] < min(readable)
        raise ProtocolError("version", f"{expected.KIND} of schema version {doc.get('v')!r}, this build reads "
                                       f"{', '.join(map(str, readable))}"
                            + (" (the sender runs an older swarmmap: run one version across the team)" if older else ""))
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
