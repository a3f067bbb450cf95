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

import numpy as np

from swarmmap.shared.wire.protocol import SCALE_CHUNK, State, StateBody, Tensor

log = logging.getLogger("compression")

COMPRESSIONS = ("none", "f16", "bf16", "topk", "sign", "quant", "lowrank")
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


class Compressor:
    """The sender's side: turns each new State's vector into the body of a :class:`State`."""

    def __init__(self, mode: str, density: float = 0.01, keyframe_every: int = 100, bits: int = 3, rank: int = 1,
                 matrices: list[tuple[int, int, int]] | None = None):
        """``matrices`` (lowrank): (offset, rows, cols) of each weight matrix in the vector, row-major;
        those a rank-``rank`` product would not shrink go as plain differences."""
        if mode not in COMPRESSIONS:
            raise ValueError(f"unknown compression {mode!r}; allowed: {', '.join(COMPRESSIONS)}")
        if not 0 < density <= 1:
            raise ValueError(f"topk density must lie in (0, 1], got {density}")
        if not 2 <= bits <= 16:
            raise ValueError(f"quant bits must lie in 2..16, got {bits}")
        if rank < 1:
            raise ValueError(f"lowrank rank must be at least 1, got {rank}")
        self.mode, self.density, self.keyframe_every, self.bits = mode, density, max(1, keyframe_every), bits
        self.blocks = [(o, r, c, rank) for o, r, c in sorted(matrices or []) if rank * (r + c) < r * c]
        self.q: dict[int, np.ndarray] = {}  # lowrank: each block's Q, the next power iteration's start
        self.rng = np.random.default_rng(0)
        self.replica: np.ndarray | None = None
        self.seq = -1
        self.since_keyframe = 0
        self.warned = False

    def body(self, params: np.ndarray, keyframe: bool = False) -> StateBody:
        """The body of a State carrying ``params`` (its encoding and what that needs);
        ``keyframe`` forces a whole vector (a State sent again for an older round)."""
        vec = np.ascontiguousarray(params, dtype=np.float32)
        if self.mode == "none":
            return StateBody(Tensor.of(vec, "<f4"))
        if self.mode == "bf16":
            return StateBody(Tensor.of(to_bf16_bits(vec), "<u2"), "bf16")
        if self.mode == "f16":
            peak = float(np.abs(vec).max()) if vec.size else 0.0
            if peak <= F16_MAX:
                return StateBody(Tensor.of(vec.astype(np.float16), "<f2"), "f16")
            if not self.warned:
                self.warned = True
                log.warning("a State holds %.3g, beyond half precision (%.0f): sent as float32 (further ones too, "
                            "without a word)", peak, F16_MAX)
            return StateBody(Tensor.of(vec, "<f4"))
        self.seq += 1
        if keyframe or self.replica is None or self.replica.shape != vec.shape or self.since_keyframe + 1 >= self.keyframe_every:
            self.since_keyframe = 0
            if self.mode == "quant":
                self.replica = np.zeros_like(vec)
                return self._quant(vec, KEYFRAME_BITS, None)
            self.replica = vec.copy()
            return StateBody(Tensor.of(vec, "<f4"), seq=self.seq)
        self.since_keyframe += 1
        diff = vec - self.replica
        if self.mode == "quant":
            return self._quant(diff, self.bits, self.seq - 1)
        if self.mode == "lowrank":
            return self._lowrank(diff)
        if self.mode == "sign":
            runs = np.abs(_runs(diff))
            counts = np.full(len(runs), SCALE_CHUNK, np.float32)
            counts[-1] = diff.size - (len(runs) - 1) * SCALE_CHUNK
            scales = (runs.sum(1) / counts).astype(np.float32)
            up = diff >= 0
            self.replica += sign_steps(up, scales)
            return StateBody(Tensor.of(np.packbits(up), "|u1"), "sign", size=int(diff.size), seq=self.seq,
                             base=self.seq - 1, scales=Tensor.of(scales, "<f4"))
        k = min(diff.size, max(1, math.ceil(self.density * diff.size)))
        idx = np.argpartition(np.abs(diff), diff.size - k)[diff.size - k :] if k < diff.size else np.arange(diff.size)
        idx = np.sort(idx).astype(np.uint32)
        values = diff[idx]
        self.replica[idx] += values
        return StateBody(Tensor.of(values, "<f4"), "topk", size=int(diff.size), indices=Tensor.of(idx, "<u4"),
                         seq=self.seq, base=self.seq - 1)

    def _quant(self, diff: np.ndarray, bits: int, base: int | None) -> StateBody:
        codes, steps = quantise(diff, bits)
        self.replica += dequantise(codes, steps, bits)
        return StateBody(Tensor.of(deflate_codes(codes), "|u1"), "quant", size=int(diff.size), seq=self.seq, base=base,
                         scales=Tensor.of(steps, "<f4"), bits=bits)

    def _lowrank(self, diff: np.ndarray) -> StateBody:
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
