"""Compressed States (``learner.compression``): what a learner sends instead of its float32 vector.

Modes:

- ``none``: the float32 vector (4 bytes a value).
- ``f16`` / ``bf16``: the vector rounded to half precision or bfloat16 (2 bytes a value). Each
  State stands alone, so a lost one costs nothing later. A vector with values beyond half
  precision's range goes as float32 (bf16 has float32's range).
- ``topk``: top-k sparsification with error feedback, against the vector the receivers hold.
  The sender keeps a replica of what its receivers reconstruct; each State carries the
  ``density`` x n largest differences between its vector and that replica (indices and
  float32 values), and the replica takes them. What a State leaves out stays in the
  difference and goes in a later one (the error feedback), so nothing is lost, only delayed.
  Every ``keyframe_every``-th State, and every State sent again for an older round (to a
  neighbour that restarted), is a key frame: the whole float32 vector, which resets the
  replicas. States are numbered (``seq``) and each update names the one it adds to (``base``):
  a receiver that missed one cannot rebuild the vector and waits for the next key frame
  (:class:`Decompressor` says so). Costs 8 bytes a kept value, plus 4 n / keyframe_every.
- ``sign``: the same chain, but every value moves every State: the sign of each difference
  (one bit) times the mean absolute difference of its run of SCALE_CHUNK values (scaled sign
  compression with error feedback, as in Karimireddy et al. 2019 and CHOCO-SGD). Costs
  n / 8 + 4 n / 256 bytes (about 28 x fewer than float32), plus the key frames.
- ``quant``: the same chain, every value quantised to ``bits`` bits (``learner.quant_bits``,
  2-8): the 2^(bits-1) - 1 steps either side of zero, the step of each run of SCALE_CHUNK
  values its largest difference over that many. Unlike sign, one State can carry a
  difference of any size, to within half a step, so the copies the receivers hold stay close
  behind the parameters (CHOCO-SGD's quantised gossip). The codes, one byte each, are
  Huffman-coded (deflate): differences cluster near zero, so a 3-bit code takes 1.4-2.2 bits.
  Key frames are quant States too, of the vector itself at 16 bits (an 8-bit one put a jump
  into every copy that the chain then took rounds to close). Costs at most
  bits x n / 8 + 4 n / 256 bytes, plus at most 2 n / keyframe_every for the key frames.

- ``lowrank``: the same chain, every weight matrix's difference sent as the product of two
  thin factors, P (rows x rank) and Q (cols x rank), found by power iteration warm-started
  from the previous State's Q (PowerGossip, Vogels et al. 2020, over the chain of a broadcast
  instead of a pair of robots); what the product leaves out stays in the difference (error
  feedback). Two iterations a State, not PowerGossip's one: with one, the start (the last
  State's row space) locks onto what the last State left owed rather than the new change,
  and where the change turns to new directions each State that debt grew without bound
  (tests/shared/wire/test_compression.py's low-rank drift: 5e-6 to 0.7 in five States).
  Biases and any matrix too small to gain go as float32 differences. Costs
  4 (rank (rows + cols)) bytes a matrix instead of 4 rows cols, plus the key frames (float32).
  The receivers form P Q^T in float64 and round it, so their copies match the sender's.

One replica serves every neighbour: a State is published once to all of them (Zenoh pub/sub),
so the differences are against the last States sent to the links, as one.
"""

from __future__ import annotations

import logging
import math
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from swarmmap.shared import plugins
from swarmmap.shared.plugins import CompressionPlugin
from swarmmap.shared.wire.protocol import SCALE_CHUNK, State, StateBody, Tensor

log = logging.getLogger("compression")

KEYFRAME_BITS = 16  # a quant key frame: the vector itself, to within half of 1/32767 of each run's largest value
F16_MAX = float(np.finfo(np.float16).max)


def to_bf16_bits(values: np.ndarray) -> np.ndarray:
    """float32 -> bfloat16 (round to nearest even) as uint16 bits."""
    bits = np.ascontiguousarray(values, dtype=np.float32).view(np.uint32)
    rounded = bits + np.uint32(0x7FFF) + ((bits >> np.uint32(16)) & np.uint32(1))
    return (rounded >> np.uint32(16)).astype(np.uint16)


def from_bf16_bits(bits: np.ndarray) -> np.ndarray:
    """bfloat16 bits (uint16) -> float32."""
    return (bits.astype(np.uint32) << np.uint32(16)).view(np.float32)


@dataclass(frozen=True)
class Knobs:
    """What a compression is made with: the learner's knobs (``learner.topk_density``,
    ``keyframe_every``, ``quant_bits``, ``lowrank_rank``, ``compression_options`` validated by the
    plug-in's own model) and the network's weight matrices, (offset, rows, cols) each, row-major."""

    density: float = 0.01
    keyframe_every: int = 100
    bits: int = 3
    rank: int = 1
    matrices: tuple[tuple[int, int, int], ...] = ()
    options: Any = None

    def __post_init__(self) -> None:
        if not 0 < self.density <= 1:
            raise ValueError(f"topk density must lie in (0, 1], got {self.density}")
        if not 2 <= self.bits <= 16:
            raise ValueError(f"quant bits must lie in 2..16, got {self.bits}")
        if self.rank < 1:
            raise ValueError(f"lowrank rank must be at least 1, got {self.rank}")


class Encoder:
    """The sender's side of a compression: turns each new State's vector into the body of a
    :class:`State` in one of the wire's encodings (:data:`~swarmmap.shared.wire.protocol.STATE_ENCODINGS`),
    so that every receiver rebuilds it without knowing the compression. ``seq``: the number of the
    newest State of its chain (-1 for States that stand alone); ``replica``: the vector the
    receivers hold (None where each State stands alone); ``plain``: its bodies are the float32
    vector itself (the link may send the node's buffer as it is); ``knobs``: what it was made with."""

    plain = False
    seq = -1
    replica: np.ndarray | None = None

    def __init__(self, knobs: Knobs | None = None):
        self.knobs = knobs if knobs is not None else Knobs()

    def body(self, params: np.ndarray, keyframe: bool = False) -> StateBody:
        """The body of a State carrying ``params``; ``keyframe`` asks for one that stands alone (a State
        sent again for an older round)."""
        raise NotImplementedError


class Plain(Encoder):
    """``none``: the float32 vector."""

    plain = True

    def body(self, params: np.ndarray, keyframe: bool = False) -> StateBody:
        return StateBody(Tensor.of(np.ascontiguousarray(params, dtype=np.float32), "<f4"))


class BFloat(Encoder):
    """``bf16``: the vector rounded to bfloat16."""

    def body(self, params: np.ndarray, keyframe: bool = False) -> StateBody:
        return StateBody(Tensor.of(to_bf16_bits(params), "<u2"), "bf16")


class Half(Encoder):
    """``f16``: the vector rounded to half precision; one beyond its range goes as float32 (said once)."""

    def __init__(self, knobs: Knobs | None = None):
        super().__init__(knobs)
        self.warned = False

    def body(self, params: np.ndarray, keyframe: bool = False) -> StateBody:
        vec = np.ascontiguousarray(params, dtype=np.float32)
        peak = float(np.abs(vec).max()) if vec.size else 0.0
        if peak <= F16_MAX:
            return StateBody(Tensor.of(vec.astype(np.float16), "<f2"), "f16")
        if not self.warned:
            self.warned = True
            log.warning("a State holds %.3g, beyond half precision (%.0f): sent as float32 (further ones too, "
                        "without a word)", peak, F16_MAX)
        return StateBody(Tensor.of(vec, "<f4"))


class Chain(Encoder):
    """A chain of differences with error feedback: each State adds to the one before it, against
    ``replica`` (what the receivers hold); every ``keyframe_every``-th State, one asked for, the
    first and one after the vector's size changed is a key frame. A subclass says what an update
    carries (:meth:`update`) and may make its key frames its own way (:meth:`keyframe`)."""

    def __init__(self, knobs: Knobs):
        super().__init__(knobs)
        self.keyframe_every = max(1, knobs.keyframe_every)
        self.replica: np.ndarray | None = None
        self.seq = -1
        self.since_keyframe = 0

    def body(self, params: np.ndarray, keyframe: bool = False) -> StateBody:
        vec = np.ascontiguousarray(params, dtype=np.float32)
        self.seq += 1
        if keyframe or self.replica is None or self.replica.shape != vec.shape or self.since_keyframe + 1 >= self.keyframe_every:
            self.since_keyframe = 0
            return self.keyframe(vec)
        self.since_keyframe += 1
        return self.update(vec - self.replica)

    def keyframe(self, vec: np.ndarray) -> StateBody:
        """A State that stands alone (the float32 vector numbered ``seq``); the replica starts again."""
        self.replica = vec.copy()
        return StateBody(Tensor.of(vec, "<f4"), seq=self.seq)

    def update(self, diff: np.ndarray) -> StateBody:
        """A State adding to the previous one what it carries of ``diff``; the replica takes it."""
        raise NotImplementedError


class TopK(Chain):
    """``topk``: the ``density`` x n largest differences, at their indices."""

    def update(self, diff: np.ndarray) -> StateBody:
        k = min(diff.size, max(1, math.ceil(self.knobs.density * diff.size)))
        idx = np.argpartition(np.abs(diff), diff.size - k)[diff.size - k :] if k < diff.size else np.arange(diff.size)
        idx = np.sort(idx).astype(np.uint32)
        values = diff[idx]
        self.replica[idx] += values
        return StateBody(Tensor.of(values, "<f4"), "topk", size=int(diff.size), indices=Tensor.of(idx, "<u4"),
                         seq=self.seq, base=self.seq - 1)


class Sign(Chain):
    """``sign``: every difference's sign times its run's mean absolute difference."""

    def update(self, diff: np.ndarray) -> StateBody:
        runs = np.abs(_runs(diff))
        counts = np.full(len(runs), SCALE_CHUNK, np.float32)
        counts[-1] = diff.size - (len(runs) - 1) * SCALE_CHUNK
        scales = (runs.sum(1) / counts).astype(np.float32)
        up = diff >= 0
        self.replica += sign_steps(up, scales)
        return StateBody(Tensor.of(np.packbits(up), "|u1"), "sign", size=int(diff.size), seq=self.seq,
                         base=self.seq - 1, scales=Tensor.of(scales, "<f4"))


class Quant(Chain):
    """``quant``: every difference quantised to ``bits`` bits, the codes Huffman-coded; key frames
    are quant States of the vector itself at KEYFRAME_BITS."""

    def keyframe(self, vec: np.ndarray) -> StateBody:
        self.replica = np.zeros_like(vec)
        return self._quant(vec, KEYFRAME_BITS, None)

    def update(self, diff: np.ndarray) -> StateBody:
        return self._quant(diff, self.knobs.bits, self.seq - 1)

    def _quant(self, diff: np.ndarray, bits: int, base: int | None) -> StateBody:
        codes, steps = quantise(diff, bits)
        self.replica += dequantise(codes, steps, bits)
        return StateBody(Tensor.of(deflate_codes(codes), "|u1"), "quant", size=int(diff.size), seq=self.seq, base=base,
                         scales=Tensor.of(steps, "<f4"), bits=bits)


class LowRank(Chain):
    """``lowrank``: each weight matrix's difference as P Q^T of rank ``rank`` (two power iterations
    warm-started from the last State's Q); those a product would not shrink, and biases, as they are."""

    def __init__(self, knobs: Knobs):
        super().__init__(knobs)
        rank = knobs.rank
        self.blocks = [(o, r, c, rank) for o, r, c in sorted(knobs.matrices) if rank * (r + c) < r * c]
        self.q: dict[int, np.ndarray] = {}  # each block's Q, the next power iteration's start
        self.rng = np.random.default_rng(0)

    def update(self, diff: np.ndarray) -> StateBody:
        parts = []
        blocks = [b for b in self.blocks if b[0] + b[1] * b[2] <= diff.size]
        for offset, rows, cols, rank in blocks:
            m = diff[offset : offset + rows * cols].reshape(rows, cols).astype(np.float64)
            q = self.q.get(offset)
            if q is None or q.shape != (cols, rank) or not q.any():
                q = self.rng.standard_normal((cols, rank))
            for _ in range(2):  # power iterations: P orthonormal, then Q = M^T P
                p, _ = np.linalg.qr(m @ q)
                q = m.T @ p
            self.q[offset] = q
            p32, q32 = p.astype(np.float32), q.astype(np.float32)
            parts += [p32.reshape(-1), q32.reshape(-1)]
        values = np.concatenate([*parts, diff[uncovered(blocks, diff.size)]]).astype(np.float32)
        self.replica += lowrank_update(values, blocks, diff.size)
        return StateBody(Tensor.of(values, "<f4"), "lowrank", size=int(diff.size), seq=self.seq, base=self.seq - 1,
                         blocks=[list(b) for b in blocks])


# swarmmap's compressions, registered in its pyproject.toml (entry points swarmmap.compressions)
NONE = CompressionPlugin(Plain, "float32, 4 bytes a value")
F16 = CompressionPlugin(Half, "half precision, 2 bytes a value (float32 beyond its range)")
BF16 = CompressionPlugin(BFloat, "bfloat16, 2 bytes a value")
TOPK = CompressionPlugin(TopK, "the topk_density largest differences, with error feedback", chained=True)
SIGN = CompressionPlugin(Sign, "each difference's sign, a scale per 256, with error feedback (about 28x fewer bytes)",
                         chained=True)
QUANT = CompressionPlugin(Quant, "each difference in quant_bits bits, a step per 256, Huffman-coded, with error feedback",
                          chained=True)
LOWRANK = CompressionPlugin(LowRank, "each weight matrix's difference as a rank-lowrank_rank product (PowerGossip), "
                                     "with error feedback", chained=True)


def compressor(mode: str, density: float = 0.01, keyframe_every: int = 100, bits: int = 3, rank: int = 1,
               matrices: list[tuple[int, int, int]] | None = None, options: Any = None) -> Encoder:
    """The encoder of the compression plug-in called ``mode`` (``learner.compression``), made with these
    knobs; a ValueError for a knob out of range, a PluginError for a compression that is not installed,
    fails to import or makes no Encoder."""
    knobs = Knobs(density, keyframe_every, bits, rank, tuple(tuple(m) for m in matrices or ()), options)
    spec = plugins.load("compressions", mode)
    try:
        encoder = spec.make(knobs)
    except Exception as exc:  # whatever a foreign part raises is that part's fault
        raise plugins.broken_contract(mode, "compressions", f"make raised {type(exc).__name__}: {exc}") from None
    if not isinstance(encoder, Encoder):
        raise plugins.broken_contract(mode, "compressions", f"it made a {type(encoder).__name__}, not an Encoder "
                                                            "(swarmmap.shared.wire.compression)")
    return encoder


def lowrank_update(values: np.ndarray, blocks, size: int) -> np.ndarray:
    """The update a lowrank State's ``values`` stand for: each block's P Q^T (formed in float64,
    so that sender and receivers round alike), then the plain differences everywhere else."""
    out = np.empty(size, np.float32)
    at = 0
    for offset, rows, cols, rank in blocks:
        p = values[at : at + rows * rank].reshape(rows, rank).astype(np.float64)
        q = values[at + rows * rank : at + (rows + cols) * rank].reshape(cols, rank).astype(np.float64)
        at += (rows + cols) * rank
        out[offset : offset + rows * cols] = (p @ q.T).astype(np.float32).reshape(-1)
    out[uncovered(blocks, size)] = values[at:]
    return out


def uncovered(blocks, size: int) -> np.ndarray:
    """Which of a vector's ``size`` values no lowrank block covers (they travel as they are)."""
    rest = np.ones(size, bool)
    for offset, rows, cols, _ in blocks:
        rest[offset : offset + rows * cols] = False
    return rest


def _runs(values: np.ndarray) -> np.ndarray:
    """``values`` zero-padded to whole runs of SCALE_CHUNK, one run a row."""
    padded = np.zeros(-(-values.size // SCALE_CHUNK) * SCALE_CHUNK, np.float32)
    padded[: values.size] = values
    return padded.reshape(-1, SCALE_CHUNK)


def per_value(steps: np.ndarray, count: int) -> np.ndarray:
    """Each run's step (or scale), repeated for each of its values: the first ``count``."""
    return np.repeat(steps, SCALE_CHUNK)[:count]


def code_dtype(bits: int) -> np.dtype:
    """Codes of up to 8 bits take a byte, longer ones (key frames) two, little-endian."""
    return np.dtype(np.uint8 if bits <= 8 else "<u2")


def quantise(values: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Codes (:func:`code_dtype`, 0 .. 2^bits - 2) and the step of each run of SCALE_CHUNK values: each value
    rounded to the nearest of the 2^(bits-1) - 1 steps either side of zero, the run's largest
    magnitude at the outermost step."""
    levels = (1 << (bits - 1)) - 1
    runs = _runs(values)
    steps = (np.abs(runs).max(1) / levels).astype(np.float32)
    scaled = runs / np.where(steps > 0, steps, 1)[:, None]
    codes = (np.clip(np.rint(scaled), -levels, levels) + levels).astype(code_dtype(bits)).reshape(-1)[: values.size]
    return codes, steps


def dequantise(codes: np.ndarray, steps: np.ndarray, bits: int) -> np.ndarray:
    """The values that codes stand for (any code 0 .. 2^bits - 1 gives a finite value)."""
    levels = (1 << (bits - 1)) - 1
    return ((codes.astype(np.float32) - levels) * per_value(steps, codes.size)).astype(np.float32)


def deflate_codes(codes: np.ndarray) -> np.ndarray:
    """Codes (one or two bytes each) Huffman-coded (raw deflate without string matching: the codes of
    differences are mostly near zero, so they take about as many bits as their entropy, 1.4-2.2
    for 3-bit codes, instead of 3)."""
    z = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zlib.Z_HUFFMAN_ONLY)
    return np.frombuffer(z.compress(codes.tobytes()) + z.flush(), np.uint8)


def inflate_codes(data: np.ndarray, count: int, bits: int) -> np.ndarray:
    """The ``count`` codes of :func:`deflate_codes`; ValueError for anything else (a stream that is
    broken, holds more or fewer codes, or codes beyond ``bits``). Never inflates past ``count``."""
    dtype = code_dtype(bits)
    z = zlib.decompressobj(-15)
    try:
        raw = z.decompress(data.tobytes(), max(1, count * dtype.itemsize))  # 0 would mean no limit
    except zlib.error as e:
        raise ValueError(f"its codes are not a deflate stream ({e})") from None
    if len(raw) != count * dtype.itemsize or not z.eof or z.unconsumed_tail or z.unused_data:
        raise ValueError(f"its codes stream does not hold exactly {count} codes")
    codes = np.frombuffer(raw, dtype)
    if count and int(codes.max()) >= 1 << bits:
        raise ValueError(f"it holds codes beyond {bits} bits")
    return codes


def sign_steps(up: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """A sign State's step per value: + or - the scale of its run of SCALE_CHUNK values."""
    step = per_value(scales, up.size)
    return np.where(up, step, -step).astype(np.float32)


class Decompressor:
    """The receivers' side: the float32 vector a State stands for, per sender (each sender's
    topk replica is kept). :meth:`vector` returns None when a topk State cannot be rebuilt (an
    update whose base this receiver missed), with the reason in ``why``."""

    def __init__(self) -> None:
        self.replicas: dict[int, tuple[int, np.ndarray]] = {}  # sender -> (seq, vector)
        self.why = ""
        self.broken = 0  # topk States that could not be rebuilt

    def vector(self, msg: State) -> np.ndarray | None:
        """The State's vector, float32 (read-only for an uncompressed State: a view of the payload)."""
        if msg.encoding == "f32":
            vec = msg.params.numpy()
            if msg.seq is not None:  # a key frame: the sender's chain starts again here
                self.replicas[msg.sender] = (msg.seq, vec.copy())
            return vec
        if msg.encoding == "f16":
            return msg.params.numpy().astype(np.float32)
        if msg.encoding == "bf16":
            return from_bf16_bits(msg.params.numpy())
        held = self.replicas.get(msg.sender)
        if msg.encoding == "quant" and msg.base is None:  # a key frame
            held = (None, np.zeros(msg.size, np.float32))
        elif held is not None and held[0] == msg.seq and held[1].size == msg.size:
            return held[1].copy()  # the same State again (a resend)
        if held is None or held[0] != msg.base or held[1].size != msg.size:
            self.broken += 1
            self.why = (f"{msg.encoding} State {msg.seq} of node {msg.sender} adds to its State {msg.base}, "
                        + ("but none of its key frames has arrived yet" if held is None else f"but the last one here is {held[0]}")
                        + ": waiting for its next key frame")
            return None
        vec = held[1]
        if msg.encoding == "quant":
            try:
                codes = inflate_codes(msg.params.numpy(), msg.size, msg.bits)
            except ValueError as e:
                self.broken += 1
                self.why = f"quant State {msg.seq} of node {msg.sender} is refused: {e}; waiting for its next key frame"
                return None
            vec += dequantise(codes, msg.scales.numpy(), msg.bits)
        elif msg.encoding == "lowrank":
            vec += lowrank_update(msg.params.numpy(), msg.blocks, msg.size)
        elif msg.encoding == "sign":
            vec += sign_steps(np.unpackbits(msg.params.numpy(), count=msg.size).astype(bool), msg.scales.numpy())
        else:
            vec[msg.indices.numpy()] += msg.params.numpy()
        self.replicas[msg.sender] = (msg.seq, vec)
        return vec.copy()

    def forget(self, sender: int) -> None:
        """Drop a sender's replica (it restarted: its next chain starts with a key frame)."""
        self.replicas.pop(sender, None)
