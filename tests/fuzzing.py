"""What the fuzz tests share: valid inputs mutated a few bytes at a time (hypothesis strategies)."""

from __future__ import annotations

from hypothesis import strategies as st


@st.composite
def mutation_of(draw, data: bytes) -> bytes:
    """``data`` with a few bytes changed, cut out, inserted or repeated, or cut short."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, max(len(out) - 1, 0)))
        how = draw(st.sampled_from(["flip", "cut", "insert", "repeat", "truncate"]))
        if how == "flip" and out:
            out[at] ^= draw(st.integers(1, 255))
        elif how == "cut":
            del out[at : at + draw(st.integers(1, 64))]
        elif how == "insert":
            out[at:at] = draw(st.binary(min_size=1, max_size=32))
        elif how == "repeat":
            out[at:at] = out[at : at + draw(st.integers(1, 64))] * draw(st.integers(1, 32))
        else:
            del out[at:]
    return bytes(out)
