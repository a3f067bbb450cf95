"""CubiCasa5K floor-plan SVGs (``model.svg``) as metric 2-D polygons: walls, railings, doors, windows and rooms.

Run-book: ``plan = load_cubicasa("cubicasa5k/353/model.svg")`` returns every outline as a (K, 2) float64 array in
world metres, x right and y up: the SVG's y axis is flipped about its height (viewBox, else ``height``) and one SVG
unit is ``scale_m_per_unit`` metres (0.01, since the dataset's units are about 1 cm). Walls, railings and windows
are solid; doors are openings; rooms carry their CubiCasa type ("Kitchen", "Bedroom", ...). Transforms of an
element and all its ancestors are applied. Anything unusable raises :class:`PlanError` naming the file and the
problem; hostile input (over 50 MB, any DOCTYPE/ENTITY declaration) is refused before it is parsed.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from xml.parsers import expat

import numpy as np

from swarmmap.shared.world.floorplan import PlanError, missing

MAX_BYTES = 50 * 1024 * 1024
MAX_DEPTH = 256  # CubiCasa nests ~15 deep; the limit keeps hostile nesting from blowing the recursion
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_SEP = re.compile(r"[\s,]+")
_TRANSFORM = re.compile(r"\s*([A-Za-z]+)\s*\(([^()]*)\)\s*,?")
_ARITY = {"matrix": (6,), "translate": (1, 2), "scale": (1, 2), "rotate": (1, 3), "skewX": (1,), "skewY": (1,)}
_KIND_BY_ID = {"Wall": "wall", "Railing": "railing", "Door": "door", "Window": "window"}


@dataclass
class CubiCasaPlan:
    """A CubiCasa5K floor plan in metres (x right, y up); every polygon is a (K, 2) float64 array."""

    walls: list[np.ndarray]
    railings: list[np.ndarray]
    doors: list[np.ndarray]
    windows: list[np.ndarray]
    rooms: list[tuple[str, np.ndarray]]
    width_m: float
    height_m: float


def load_cubicasa(path: str | Path, scale_m_per_unit: float = 0.01) -> CubiCasaPlan:
    """Read and parse a CubiCasa5K ``model.svg``; raises :class:`PlanError` if it is missing, unreadable or bad."""
    p = Path(path)
    try:
        if not p.exists():
            raise PlanError(str(p), missing(p))
        size = p.stat().st_size
        if size > MAX_BYTES:
            raise PlanError(str(p), f"file is {size} bytes, over the {MAX_BYTES >> 20} MB limit")
        with p.open("rb") as f:
            data = f.read(MAX_BYTES + 1)  # +1: a file that grew after stat() still trips the limit
    except OSError as e:
        raise PlanError(str(p), f"cannot read file: {e.strerror or e}") from e
    return parse_cubicasa(data, str(p), scale_m_per_unit)


def parse_cubicasa(svg_text: str | bytes, source: str = "<svg>", scale_m_per_unit: float = 0.01) -> CubiCasaPlan:
    """Parse CubiCasa5K SVG text; ``source`` names it in :class:`PlanError` messages."""
    if not (math.isfinite(scale_m_per_unit) and scale_m_per_unit > 0):
        raise ValueError(f"scale_m_per_unit must be positive and finite, got {scale_m_per_unit}")
    if len(svg_text) > MAX_BYTES:
        raise PlanError(source, f"document is over the {MAX_BYTES >> 20} MB limit")
    root = _parse_xml(svg_text, source)
    if _local(root.tag) != "svg":
        raise PlanError(source, f"not an SVG file (root element is <{_local(root.tag)}>)")
    found: dict[str, list[tuple[str, np.ndarray]]] = {k: [] for k in ("wall", "railing", "door", "window", "room")}
    _visit(root, (root,), found, source)
    if not found["wall"]:
        raise PlanError(source, 'no <g id="Wall"> found: not a CubiCasa5K floor plan')
    solid = [pts for kind in ("wall", "railing", "room") for _, pts in found[kind]]
    height = _svg_height(root, source)
    if height is None:
        height = max(float(pts[:, 1].max()) for kinds in found.values() for _, pts in kinds)

    def metres(pts: np.ndarray) -> np.ndarray:
        return np.column_stack((pts[:, 0] * scale_m_per_unit, (height - pts[:, 1]) * scale_m_per_unit))

    extent = np.ptp(np.concatenate(solid), axis=0) * scale_m_per_unit
    return CubiCasaPlan(
        walls=[metres(p) for _, p in found["wall"]],
        railings=[metres(p) for _, p in found["railing"]],
        doors=[metres(p) for _, p in found["door"]],
        windows=[metres(p) for _, p in found["window"]],
        rooms=[(label, metres(p)) for label, p in found["room"]],
        width_m=float(extent[0]),
        height_m=float(extent[1]),
    )


def _parse_xml(data: str | bytes, source: str) -> ET.Element:
    marks = ("<!DOCTYPE", "<!ENTITY") if isinstance(data, str) else (b"<!DOCTYPE", b"<!ENTITY")
    refusal = "document declares a DOCTYPE/ENTITY, refused (entity-expansion risk)"
    if any(m in data for m in marks):
        raise PlanError(source, refusal)

    def refuse(*_: object) -> None:
        raise PlanError(source, refusal)

    # The substring test misses declarations in UTF-16 or other declared encodings; expat sees them all.
    probe = expat.ParserCreate()
    probe.StartDoctypeDeclHandler = refuse
    probe.EntityDeclHandler = refuse
    try:
        probe.Parse(data, True)
        return ET.fromstring(data)
    except (expat.ExpatError, ET.ParseError) as e:
        raise PlanError(source, f"not a valid SVG/XML: {e}") from None


def _local(tag: object) -> str:
    return tag.rsplit("}", 1)[-1] if isinstance(tag, str) else ""


def _describe(el: ET.Element) -> str:
    attrs = "".join(f' {k}="{el.get(k)}"' for k in ("id", "class") if el.get(k))
    return f"<{_local(el.tag)}{attrs}>"


def _numbers(text: str, what: str, source: str) -> list[float]:
    out = []
    for tok in _SEP.split(text):
        if not tok:
            continue  # leading/trailing separators
        if not _NUMBER.fullmatch(tok):
            raise PlanError(source, f"{what} has a non-numeric value {tok!r}")
        value = float(tok)
        if not math.isfinite(value):
            raise PlanError(source, f"{what} has a non-finite value {tok!r}")
        out.append(value)
    return out


def _svg_height(root: ET.Element, source: str) -> float | None:
    box = root.get("viewBox")
    if box is not None:
        nums = _numbers(box, "the viewBox", source)
        if len(nums) != 4 or nums[3] <= 0:
            raise PlanError(source, f"cannot parse viewBox {box!r}: need 4 numbers and a positive height")
        return nums[1] + nums[3]  # the viewport's bottom edge in user units
    m = re.fullmatch(rf"\s*({_NUMBER.pattern})\s*(?:px)?\s*", root.get("height", ""))
    return float(m.group(1)) if m and 0 < float(m.group(1)) < math.inf else None  # "100%", "29cm": unusable


def _transform(text: str, owner: ET.Element, source: str) -> np.ndarray:
    """The 3x3 matrix of an SVG transform list (applied right to left, as SVG composes them)."""
    bad = f"cannot parse transform {text!r} on {_describe(owner)}"
    m, pos, text = np.eye(3), 0, text.strip()
    while pos < len(text):
        call = _TRANSFORM.match(text, pos)
        if call is None or call.group(1) not in _ARITY:
            raise PlanError(source, bad)
        name, a = call.group(1), _numbers(call.group(2), f"transform on {_describe(owner)}", source)
        if len(a) not in _ARITY[name]:
            raise PlanError(source, f"{bad}: {name}() takes {' or '.join(map(str, _ARITY[name]))} numbers")
        if name == "matrix":
            step = [[a[0], a[2], a[4]], [a[1], a[3], a[5]], [0, 0, 1]]
        elif name == "translate":
            step = [[1, 0, a[0]], [0, 1, a[1] if len(a) > 1 else 0], [0, 0, 1]]
        elif name == "scale":
            step = [[a[0], 0, 0], [0, a[-1], 0], [0, 0, 1]]
        elif name == "rotate":
            c, s = math.cos(math.radians(a[0])), math.sin(math.radians(a[0]))
            cx, cy = (a[1], a[2]) if len(a) == 3 else (0.0, 0.0)
            step = [[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy], [0, 0, 1]]
        else:
            t = math.tan(math.radians(a[0]))
            step = [[1, t, 0], [0, 1, 0], [0, 0, 1]] if name == "skewX" else [[1, 0, 0], [t, 1, 0], [0, 0, 1]]
        m = m @ np.array(step, dtype=float)
        pos = call.end()
    return m


def _polygon(poly: ET.Element, chain: tuple[ET.Element, ...], what: str, source: str) -> np.ndarray:
    """The polygon's points in SVG root units, after the transforms of every element in ``chain``."""
    nums = _numbers(poly.get("points", ""), what, source)
    if len(nums) % 2:
        raise PlanError(source, f"{what} has an odd number of coordinates ({len(nums)})")
    if len(nums) < 6:
        raise PlanError(source, f"{what} has only {len(nums) // 2} points (a polygon needs at least 3)")
    m = np.eye(3)
    for el in chain:
        if el.get("transform"):
            with np.errstate(all="ignore"):
                m = m @ _transform(el.get("transform"), el, source)
    pts = np.array(nums, dtype=float).reshape(-1, 2)
    with np.errstate(all="ignore"):  # overflow is reported below as non-finite coordinates
        out = pts @ m[:2, :2].T + m[:2, 2]
    if not np.isfinite(out).all():
        raise PlanError(source, f"{what} has non-finite coordinates after its transforms")
    return out


def _descendant_polygons(el: ET.Element, chain: tuple[ET.Element, ...], source: str):
    for child in el:
        sub = chain + (child,)
        if len(sub) > MAX_DEPTH:
            raise PlanError(source, f"elements are nested more than {MAX_DEPTH} levels deep")
        if _local(child.tag) == "polygon":
            yield child, sub
        else:
            yield from _descendant_polygons(child, sub, source)


def _visit(el: ET.Element, chain: tuple[ET.Element, ...], found: dict, source: str) -> None:
    """Collect wall, railing, door, window and room outlines below ``el`` (``chain``: root .. el)."""
    for child in el:
        if _local(child.tag) != "g":
            continue
        sub = chain + (child,)
        if len(sub) > MAX_DEPTH:
            raise PlanError(source, f"elements are nested more than {MAX_DEPTH} levels deep")
        classes = (child.get("class") or "").split()
        kind = _KIND_BY_ID.get(child.get("id", "")) or ("room" if classes[:1] == ["Space"] else None)
        if kind is not None:
            what = f"{kind} polygon #{len(found[kind]) + 1}"
            hit = next(((p, sub + (p,)) for p in child if _local(p.tag) == "polygon"), None)
            if hit is None and kind in ("door", "window"):
                # Door/window outlines normally come first; otherwise take the first panel/threshold polygon.
                hit = next(_descendant_polygons(child, sub, source), None)
            if hit is None:
                raise PlanError(source, f"{what} is missing: {_describe(child)} has no <polygon> outline")
            label = (classes[1] if len(classes) > 1 else "Undefined") if kind == "room" else kind
            found[kind].append((label, _polygon(hit[0], hit[1], what, source)))
        if kind not in ("door", "window"):  # walls hold their doors and windows
            _visit(child, sub, found, source)
