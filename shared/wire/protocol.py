"""The swarmmap wire protocol: every key expression and every message, in one module.

Keys live under ``<prefix>/<run>/`` (see :class:`Keys`). Every payload is one msgpack map
with a schema version ``v`` and a ``kind``; tensors travel as ``{"dtype", "shape", "data"}``
with raw little-endian bytes, never pickle. :func:`decode` refuses anything malformed,
oversized, from another run, from a sender that does not match its key, of the wrong shape
or dtype, or non-finite, by raising :class:`ProtocolError` with a short reason.
The codec (encode, decode, copy-free State frames) is :mod:`swarmmap.shared.wire.codec`; docs/protocol.md
documents all of this for clients in other languages.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, fields
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

SCHEMA_VERSION = 2
# Versions read per message kind: a State changed in version 2 (compressed encodings), the other
# messages did not, so that those of version 1 (a recording made by an older build) are still read.
READ_VERSIONS = {"State": (2,)}
OLDEST_VERSION = 1
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
MAX_DETAIL_CHARS = 240  # a refusal's detail, at most (it names what the message held)

NAME_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
_NAME_RE = re.compile(NAME_PATTERN)

# Little-endian dtype strings a tensor may carry ("|u1" has no byte order).
TENSOR_DTYPES = ("<f4", "<f8", "<f2", "<i4", "<i8", "<u2", "<u4", "|u1")
MAX_TENSOR_DIMS = 4


class ProtocolError(ValueError):
    """A payload that a receiver refuses; ``reason`` is a short tag used for counting."""

    def __init__(self, reason: str, detail: str):
        if len(detail) > MAX_DETAIL_CHARS:  # (a detail may quote the sender's data: never unbounded into a log)
            detail = f"{detail[: MAX_DETAIL_CHARS - 40]}... ({len(detail)} characters)"
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
        learners/<id>/goal          Goal        learner -> world, neighbours, observer (exploration)
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

    def goal(self, robot: int | str) -> str:
        return f"{self.root}/learners/{robot}/goal"

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
    leg: Annotated[int, Field(ge=0, le=10**6)] | None = None  # exploration: the leg of the drive the scan belongs to
    leg_end: bool = False  # exploration: the robot's last scan of its leg

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
    leg: Annotated[int, Field(ge=0, le=10**6)] | None = None  # exploration: its scan's leg (Scan.leg)
    leg_end: bool = False

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
    come with it (see :class:`State`). A compression's :class:`~swarmmap.shared.wire.compression.Encoder` makes
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
    repeated_samples: Annotated[int, Field(ge=0)] = 0  # Samples of scans it had already (a restarted world's), dropped
    # [neighbour, messages of it refused] for each neighbour this learner refused anything of
    refused_from: Annotated[list[Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=2, max_length=2)]],
                            Field(max_length=128)] = []
    final: bool = False


MAX_GOAL_PATH = 4096  # waypoints of a Goal's path


class Goal(Message):
    """Exploration: where robot ``sender`` drives in ``leg`` of the drive, chosen at training
    round ``round`` (``x``, ``y`` metres in the plan's frame) and the path to it on its own map
    (``path`` (K, 2) float32, from the robot's position); ``done``: its policy has nowhere left to
    go (the robot stays). Learner -> world, its neighbours (they pass over goals a teammate holds),
    the observer."""

    KIND: ClassVar[str] = "Goal"
    leg: Annotated[int, Field(ge=1, le=10**6)]
    round: Round
    x: FiniteFloat = 0.0
    y: FiniteFloat = 0.0
    path: Tensor | None = None
    done: bool = False
    reason: Annotated[str, Field(max_length=200)] = ""

    @model_validator(mode="after")
    def _path(self) -> Goal:
        if self.path is not None:
            _require(self.path, "path", "<f4", 2, (2,))
            if self.path.shape[0] > MAX_GOAL_PATH:
                raise ValueError(f"path has {self.path.shape[0]} waypoints, at most {MAX_GOAL_PATH}")
        if not self.done and (self.path is None or self.path.shape[0] == 0):
            raise ValueError("a goal that is not done needs a path")
        return self


MAX_VALIDATION_POINTS = 50_000_000  # what a receiver agrees to draw (a few GB at most)


class ValidationRecipe(BaseModel):
    """How a WorldMap's validation set is drawn from its grid
    (:func:`swarmmap.shared.world.sensing.validation_set` with these arguments), and figures of the
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
    before it trains). :meth:`swarmmap.shared.wire.bus.Bus.world` draws it and checks it against
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
    cls.KIND: cls for cls in (Scan, Samples, State, RoundComplete, Metrics, Goal, WorldMap, RunDone)
}

M = TypeVar("M", bound=Message)
