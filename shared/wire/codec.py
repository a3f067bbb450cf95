"""The wire codec: a message to its msgpack payload and back, refusing anything malformed (see
:mod:`swarmmap.shared.wire.protocol` for the messages and their checks); a State's payload laid out
so that its vector is read without a copy (:class:`StateFrame`)."""

from __future__ import annotations

import functools
import math
import sys
import warnings
from dataclasses import dataclass

import msgpack
import numpy as np
from pydantic import ValidationError

from swarmmap.shared.wire.protocol import (
    _NAME_RE,
    DEFAULT_MAX_MESSAGE_BYTES,
    OLDEST_VERSION,
    READ_VERSIONS,
    SCHEMA_VERSION,
    M,
    Message,
    ProtocolError,
    State,
    Tensor,
)


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


HEADER_BYTES = 512  # a message's header (v, kind, run, sender) lies within its first bytes
HEADER_KEYS = ("v", "kind", "run", "sender")


@dataclass(frozen=True)
class Bounds:
    """What a payload of one message kind may hold, checked while it is unpacked: its bytes (None:
    the receiver's ``max_bytes``), its maps and arrays (``containers``), all its arrays' elements
    together (``items``) and one map's entries (``entries``). A legitimate message of the kind
    holds a few of each (a State's ``blocks`` one array a weight matrix): a payload of millions of
    tiny maps is refused after the first few, in microseconds, not unpacked whole."""

    max_bytes: int | None
    containers: int
    items: int
    entries: int = 32


MAX_MATRICES = 4096  # a lowrank State's blocks: one per weight matrix
BOUNDS: dict[str, Bounds] = {
    "State": Bounds(None, 16 + MAX_MATRICES, 16 + 5 * MAX_MATRICES),
    "RoundComplete": Bounds(4096, 1, 0),
    "Metrics": Bounds(16384, 2 + 128, 3 * 128),
    "RunDone": Bounds(65536, 2, 10_000),
    "Goal": Bounds(65536, 3, 8),
    "Scan": Bounds(None, 8, 16),
    "Samples": Bounds(None, 6, 16),
    "WorldMap": Bounds(None, 16, 32),
}


def read_header(payload: bytes) -> dict:
    """The header of a payload: the first entries of its top-level map, which must be v, kind,
    run and sender (:func:`encode` writes them first), read from its first HEADER_BYTES bytes
    with small limits; anything else is refused before the rest of the payload is looked at."""
    up = msgpack.Unpacker(raw=False, max_buffer_size=HEADER_BYTES, max_str_len=128, max_bin_len=0, max_array_len=0,
                          max_map_len=0, max_ext_len=0)
    up.feed(payload[:HEADER_BYTES])
    head: dict = {}
    try:
        n = up.read_map_header()
        for _ in range(min(n, len(HEADER_KEYS))):
            key = up.unpack()
            if key not in HEADER_KEYS or key in head:
                break
            head[key] = up.unpack()
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise ProtocolError("malformed", f"no message header (a map beginning with v, kind, run, sender): {exc}") from None
    if len(head) < len(HEADER_KEYS):
        raise ProtocolError("malformed", f"the header holds {sorted(head)}, not {', '.join(HEADER_KEYS)} first")
    return head


def unpack_bounded(payload: bytes, bounds: Bounds, max_bin: int) -> object:
    """``payload`` unpacked within ``bounds`` (each map and array counted as it is made); msgpack's
    own exceptions (of several types) or a ValueError when it is malformed or out of bounds."""
    made = [0, 0]  # containers, array items

    def count(obj, items: int = 0):
        made[0] += 1
        made[1] += items
        if made[0] > bounds.containers or made[1] > bounds.items:
            raise ValueError(f"more than {bounds.containers} maps and arrays or {bounds.items} array items")
        return obj

    return msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=max_bin, max_str_len=1 << 16,
                           max_array_len=max(bounds.items, 1), max_map_len=bounds.entries, max_ext_len=0,
                           object_hook=count, list_hook=lambda xs: count(xs, len(xs)))


def check_header(head: dict, expected: type[Message], run: str, sender: int | None) -> None:
    """Refuse a header of another kind, schema version, run or sender (before the body is read)."""
    if head["kind"] != expected.KIND:
        raise ProtocolError("kind", f"expected {expected.KIND}, got {head['kind']!r}")
    readable = READ_VERSIONS.get(expected.KIND, range(OLDEST_VERSION, SCHEMA_VERSION + 1))
    if head["v"] not in readable:
        older = isinstance(head["v"], int) and head["v"] < min(readable)
        raise ProtocolError("version", f"{expected.KIND} of schema version {head['v']!r}, this build reads "
                                       f"{', '.join(map(str, readable))}"
                            + (" (the sender runs an older swarmmap: run one version across the team)" if older else ""))
    if head["run"] != run:
        raise ProtocolError("wrong-run", f"run {head['run']!r}, expected {run!r}")
    if sender is not None and head["sender"] != sender:
        raise ProtocolError("unknown-sender", f"sender {head['sender']!r} on a key of {sender}")


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
    own ``sender`` differs is refused, so nobody can speak for another robot. The header (kind,
    version, run, sender) is read and judged first (:func:`read_header`), then the body within
    the kind's :data:`BOUNDS` (its bytes at most ``max_bytes``, or the kind's own limit where
    smaller), then its fields.
    """
    bounds = BOUNDS.get(expected.KIND, Bounds(None, 64, 1 << 16))
    limit = max_bytes if bounds.max_bytes is None else min(max_bytes, bounds.max_bytes)
    if len(payload) > limit:
        raise ProtocolError("oversized", f"{len(payload)} bytes > limit {limit} for a {expected.KIND}")
    if expected is State and isinstance(payload, bytes):
        fast = _decode_state_fast(payload, run, sender)
        if fast is not None:
            return fast  # type: ignore[return-value]
    check_header(read_header(payload), expected, run, sender)
    try:
        doc = unpack_bounded(payload, bounds, limit)
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise ProtocolError("malformed", f"not a {expected.KIND} within its bounds: {exc}") from None
    if not isinstance(doc, dict):
        raise ProtocolError("malformed", f"top level must be a map, got {type(doc).__name__}")
    try:
        return expected.model_validate(doc)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or expected.KIND
        reason = "non-finite" if "finite" in first["msg"] else "invalid"
        if "shape" in first["msg"] or "dtype" in first["msg"] or "bytes" in first["msg"]:
            reason = "shape"
        raise ProtocolError(reason, f"{expected.KIND}.{where}: {first['msg']}") from None
